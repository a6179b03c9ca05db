"""The live progress display a person sees at a terminal, fed the rows a run logs."""
import io

from rich.console import Console

from experiments.common import progress
from php_jax.training.config import TrainConfig


def _display(config, num_levels, rows):
  console = Console(file=io.StringIO(), force_terminal=True, width=140, record=True)
  shown = progress.TrainingProgress(config, num_levels, "runs/w", console)
  for row in rows:
    shown(row)
  shown.close()
  return console.export_text()


def test_each_level_shows_its_iterations_loss_validation_and_the_end_a_table():
  config = TrainConfig(iterations=200, strong_warmup=50)
  text = _display(config, 3, [
      {"level": 2, "capacity": 4, "view_length": 30, "seconds": 1.0},
      {"level": 2, "iteration": 100, "loss": 1.2345, "seconds": 2.0},
      {"level": 1, "capacity": 3, "view_length": 10, "seconds": 3.0},
      {"level": 1, "iteration": 250, "loss": 0.5, "seconds": 4.0},
      {"level": 0, "capacity": 9, "view_length": 9, "seconds": 5.0},
      {"level": 0, "iteration": 200, "loss": 0.1, "validation": 0.96, "seconds": 6.0},
      {"phase": "testing"},
      {"test": {"20": 1.0, "50": 0.98}, "wall_seconds": 61.0}])
  assert "level 2 (1 of 3)" in text and "100/250" in text and "loss 1.234" in text  # warm-up counted below the root
  assert "level 1 (2 of 3)" in text and "250/250" in text
  assert "level 0 (3 of 3)" in text and "200/200" in text and "best validation 0.960" in text
  assert "testing" in text and "test results" in text and "0.980" in text and "61 s in all" in text
  assert "are in runs/w" in text


def test_a_finished_run_shows_its_results_and_says_it_trained_nothing():
  text = _display(TrainConfig(), 3, [{"test": {"accuracy": 1.0}, "wall_seconds": 61.0, "finished_before": True}])
  assert "1.000" in text and "had already finished in runs/w (61 s); --overwrite trains it again" in text


def test_joint_and_flat_runs_and_other_seeds():
  config = TrainConfig(iterations=60)
  text = _display(config, 3, [{"training": "joint", "capacity": [9, 4, 3], "seconds": 1.0},
                              {"iteration": 30, "loss": 2.0, "seconds": 2.0}])
  assert "every level at once" in text and "30/60" in text
  text = _display(config, 3, [{"training": "joint", "capacity": [9, 4, 3], "seconds": 1.0},
                              {"iteration": 60, "loss": 2.0, "seconds": 2.0}, {"split_rounds": 2, "seconds": 3.0},
                              {"split_search": {"round": 0, "kept": "level 2: 3 becomes a copy of 1 for caller 0",
                                                "log_likelihood_per_step": -0.01234, "candidates": []}}])
  assert "split search" in text and "1/2" in text and "kept: level 2: 3 becomes a copy of 1 for caller 0" in text
  assert "-0.01234" in text
  text = _display(config, 3, [{"split_rounds": 1, "seconds": 3.0},
                              {"split_search": {"round": 0, "kept": "unchanged", "log_likelihood_per_step": None,
                                                "candidates": [["unchanged", None]]}}])
  assert "kept: unchanged (no stack fits a validation demonstration)" in text
  text = _display(config, 3, [{"resumed": True, "level": "joint", "iteration": None, "logged": 30},
                              {"split_search": {"round": 1, "kept": "unchanged", "log_likelihood_per_step": -0.5,
                                                "candidates": [["unchanged", -0.5]]}}])
  assert "resumed from the checkpoint: level joint\n" in text and "iteration None" not in text
  assert "split search" in text and "kept: unchanged (log-likelihood per step -0.5)" in text
  text = _display(config, None, [{"iteration": 60, "loss": 0.3, "seconds": 2.0}])
  assert "flat baseline" in text and "60/60" in text
  text = _display(config, 3, [{"seed": 1, "level": 2, "capacity": 4, "seconds": 1.0},
                              {"seed": 2, "level": 2, "iteration": 60, "loss": 9.0, "seconds": 2.0},
                              {"seed": 1, "level": 2, "iteration": 30, "loss": 1.0, "seconds": 2.0},
                              {"seed": 1, "test": {"accuracy": 1.0}, "wall_seconds": 5.0},
                              {"seed": 2, "test": {"accuracy": 0.5}, "wall_seconds": 5.0}])
  assert "30/60" in text and "loss 9" not in text  # the first seed's rows stand for all
  assert "seed 1: test results" in text and "seed 2: test results" in text and "runs/w/seed=2" in text


def test_a_warning_is_printed_whole_with_its_brackets_for_every_seed():
  text = _display(TrainConfig(), 3, [{"warning": "take '[1, 4]' then '[0, 4]'"},
                                     {"level": 2, "capacity": 4, "seconds": 1.0}])
  assert "warning: take '[1, 4]' then '[0, 4]'" in text and "level 2 (1 of 3)" in text
  text = _display(TrainConfig(iterations=60), 3, [{"seed": 2, "warning": "w2"},
                                                  {"seed": 1, "level": 2, "capacity": 4, "seconds": 1.0},
                                                  {"seed": 2, "level": 2, "iteration": 60, "loss": 9.0, "seconds": 2.0},
                                                  {"seed": 1, "level": 2, "iteration": 30, "loss": 1.0, "seconds": 2.0}])
  assert "warning: seed 2: w2" in text and "30/60" in text and "loss 9" not in text  # seed 1 still followed


def test_time_left_is_shown_only_where_the_total_is_known():
  text = _display(TrainConfig(iterations=200), 3, [{"level": 2, "capacity": 4, "view_length": 30, "seconds": 1.0},
                                                   {"level": 2, "iteration": 100, "loss": 1.0, "seconds": 2.0},
                                                   {"phase": "testing"}])
  level, testing = text.strip().splitlines()[-2:]  # the last frame drawn: the level's row, then testing's
  assert "100/200" in level and level.rstrip().endswith("left"), text
  assert "0:00:00" in testing and "left" not in testing, text


def test_candidates_show_each_its_own_lines_its_score_and_the_one_kept():
  config = TrainConfig(iterations=40)
  text = _display(config, 3, [
      {"candidate": "levelwise", "warning": "an operation may be locked out"},
      {"candidate": "levelwise", "level": 2, "capacity": 4, "view_length": 9, "seconds": 1.0},
      {"candidate": "levelwise", "level": 2, "iteration": 40, "loss": 0.5, "seconds": 2.0},
      {"candidate": "levelwise", "phase": "testing"},
      {"candidate": "levelwise", "test": {"held_out_explained": 6, "held_out_log_likelihood_per_step": -0.125},
       "wall_seconds": 9.0},
      {"candidate": "joint", "warning": "an operation may be locked out"},
      {"candidate": "joint", "training": "joint", "capacity": [6, 8, 8], "unexplained": 3, "seconds": 0.0},
      {"candidate": "joint", "iteration": 20, "loss": 0.1, "seconds": 1.0},
      {"candidate": "joint", "test": {"held_out_explained": 6, "training_explained": 50,
                                      "held_out_log_likelihood_per_step": -0.003}, "wall_seconds": 12.0},
      {"chosen": "joint", "held_out_explained": 6, "held_out_log_likelihood_per_step": -0.003},
      {"phase": "testing"},
      {"test": {"held_out_replayed": 1.0}, "wall_seconds": 23.0}])
  assert "levelwise: level 2 (1 of 3)" in text and "joint: every level at once" in text and "20/40" in text
  assert "candidate levelwise: 6 held-out demonstrations explained, log-likelihood per step -0.125" in text
  assert "joint: 3 training demonstrations fit no call stack within the counter capacities [6, 8, 8]" in text
  assert text.count("fit no call stack") == 1  # the level-wise candidate's rows give no count
  assert "candidate joint: 6 held-out and 50 training demonstrations explained, log-likelihood per step -0.003" in text
  assert "kept candidate joint (6 held-out demonstrations explained, log-likelihood per step -0.003)" in text
  assert text.count("an operation may be locked out") == 1 and "23 s in all" in text
