"""Demonstrations as data: files read and written, level views, agreement of stacks, stacks read as calls."""
