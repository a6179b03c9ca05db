"""Environments and their supervisors' hierarchies."""
