"""What the commands share: flag parsing and one-line refusals (cli), the flags of the training settings, the run
and the environment, the progress display, problem files, and what show and the report read and draw."""
