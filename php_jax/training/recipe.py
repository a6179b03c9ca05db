"""The recipe: how a run trains, read from the demonstrations where they decide it, and where they do not, a
list of candidates of which the best on held-out demonstrations is kept (`selection.train_and_choose`: the one
that explains the most demonstrations, then the likeliest).

What the demonstrations decide (`config.resolved`, for every candidate): the strong weight, the counter
capacities (the longest annotated call; `fit` adds room for longer ones, `least_capacities`), annealing and the
segmentation's length without annotation. What they leave open, and so is contested:
- with some demonstration annotated, the training mode: level-wise with every operation allowed (the
  paper's), and joint with the call graph the annotation shows (`--call_graph=operations`), unless that graph
  leaves a step of some training demonstration to no procedure. Measured: the first fails NanoCraft with 2 of
  64 annotated where the second solves it, and segments Taxi's level 2 less well with 16 of 64 (RESULTS.md);
- with nothing annotated (joint training), where the segmentation starts from: each rule of
  `segmentation.RULES` that applies to the actions, and none. A rule can mislead (the successors rule on
  addition), so none is always a candidate.
Settings the user (or a task) gives are never contested. `restarts` repeats every candidate with other
initialisations (`TrainConfig.init_seed`).
"""
from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from php_jax.demos import Demonstration
from php_jax.hierarchy import HierarchySpec
from php_jax.training import call_graph, segmentation
from php_jax.training.config import MAX_SEED, TrainConfig, asks_joint, fields
from php_jax.training.objective import counter_capacity

RESTART_SEED_STRIDE = 1000  # restart r initialises from init_seed + r × this
MODE_CALL_GRAPH = {"levelwise": "all", "joint": "operations"}  # each mode's candidate call graph
SEGMENTATION_SETTINGS = ("segment_rule", "segment_iterations", "split_rounds")
UNSEGMENTED = "unsegmented"
DEFAULT_TEXT = {  # the defaults the recipe chooses, as the commands' --help states them
    "training": "the recipe's: with annotation both are tried, without it joint",
    "call_graph": "the recipe's: all for level-wise training, operations for joint training (where that leaves "
                  "a training step to no procedure, joint training is not tried, or if asked for, calls or all)",
    "segment_rule": "the recipe's: without annotation, each rule that applies is tried, and none"}


@dataclasses.dataclass(frozen=True)
class Candidate:
  """One way to train: name (a word, also its folder under the run's candidates/) and the TrainConfig
  settings it sets."""
  name: str
  settings: dict

  def config(self, base: TrainConfig) -> TrainConfig:
    return dataclasses.replace(base, **self.settings)


@dataclasses.dataclass(frozen=True)
class Recipe:
  """candidates: the ways to train (one: nothing to choose); reasons: what the demonstrations showed and
  what that decided, in words."""
  candidates: tuple[Candidate, ...]
  reasons: tuple[str, ...]

  def as_json(self) -> dict:
    return {"candidates": [{"name": c.name, "settings": c.settings} for c in self.candidates],
            "reasons": list(self.reasons)}


def choose(spec: HierarchySpec, demos: Demonstration, config: TrainConfig, given: frozenset[str] | set[str],
           restarts: int = 1, numbers: Sequence[int] | None = None) -> Recipe:
  """The recipe for training spec's hierarchy on demos from config, whose settings named in `given` were
  asked for (by a flag, a task or a hierarchy file) and are kept; restarts ≥ 1: initialisations of each
  candidate; numbers: each demonstration's number where the reasons name one (None: its index). Raises
  ValueError if restarts < 1 or the last restart's initialisation seed would pass MAX_SEED."""
  if not (isinstance(restarts, int) and restarts >= 1):
    raise ValueError(f"restarts must be a positive integer; got {restarts!r}")
  last_seed = config.network_seed + (restarts - 1) * RESTART_SEED_STRIDE
  if last_seed > MAX_SEED:
    raise ValueError(f"{restarts} restarts initialise the last from seed {last_seed}, past {MAX_SEED} (a 32-bit "
                     f"seed): give a smaller --init_seed (or --seed), or fewer restarts")
  num_strong, num = int(np.sum(demos.strong)), len(demos.length)
  mode = _fixed_mode(config, given, num_strong > 0)
  if num_strong:
    candidates, reasons = _annotated_candidates(spec, demos, given, mode, numbers)
  else:
    candidates, reasons = _discovery_candidates(spec, demos, given, mode)
  if restarts > 1:
    first = config.network_seed
    candidates = [Candidate(f"{c.name}-restart{r}", {**c.settings, "init_seed": first + r * RESTART_SEED_STRIDE})
                  if r else c for c in candidates for r in range(restarts)]  # restart 0: a run without restarts
    reasons.append(f"each is trained from {restarts} initialisations")
  if len(candidates) > 1:
    reasons.append("the candidate that explains the most demonstrations is kept, of those the one most likely "
                   "on the held-out demonstrations")
  return Recipe(tuple(candidates), tuple(reasons))


SPARE_CAPACITY = 8  # the most counters `least_capacities` asks of a level whose calls are shorter


def least_capacities(demos: Demonstration, num_levels: int, most: int = SPARE_CAPACITY) -> tuple[int, ...]:
  """`fit`'s least counter capacity per level, root first (0: joint training scales the root's itself), where
  some demonstration is annotated: each level's longest annotated call scaled by how much longer the longest
  demonstration is than the longest annotated one (the root's rule, `joint.joint_capacity`), at most `most`
  (which a level without an annotated call gets). The demonstrations without annotation may hold longer calls,
  in proportion to their length; counters to spare beyond that let a procedure count out a run of actions
  that the annotation shows it calling one at a time (NanoCraft: docs/training.md)."""
  counters, strong, lengths = np.asarray(demos.counters), np.asarray(demos.strong), np.asarray(demos.length)
  if not strong.any():
    raise ValueError("least_capacities needs an annotated demonstration")
  return (0,) + tuple(min(most, counter_capacity(counters[strong][..., level], most, 0, lengths.max(),
                                                 lengths[strong].max()))
                      for level in range(1, num_levels))


FEW_ANNOTATED, RESTARTS_WHERE_FEW = 2, 2


def restarts_where_unset(num_annotated: int) -> int:
  """`fit`'s initialisations of each candidate where --restarts is not given: RESTARTS_WHERE_FEW where 1 to
  FEW_ANNOTATED training demonstrations are annotated, else 1. With so few, a run from one initialisation can
  settle on a worse explanation that another initialisation avoids, and the held-out likelihood tells them
  apart (NanoCraft with 1 or 2 of 64 annotated: docs/training.md, the recipe)."""
  return RESTARTS_WHERE_FEW if 1 <= num_annotated <= FEW_ANNOTATED else 1


def _fixed_mode(config: TrainConfig, given, annotated: bool) -> str | None:
  """The training mode the settings fix (None: open to the recipe): the one given, joint where a setting of
  joint training only is on, level-wise where a setting of level-wise training only is given (or where
  nothing is annotated: joint, the one mode that learns a hierarchy from actions alone)."""
  if "training" in given and config.training is not None:
    return config.training
  if any(asks_joint(config, f) for f in fields()):
    return "joint"
  if any(f.name in given for f in fields() if f.metadata["levelwise_only"]):
    return "levelwise"
  return None if annotated else "joint"


def _annotated_candidates(spec: HierarchySpec, demos: Demonstration, given, mode: str | None,
                          numbers) -> tuple[list[Candidate], list[str]]:
  """The candidates with some demonstration annotated: the training modes. Joint training's call graph, the
  one the annotation shows, can leave a step of a demonstration to no procedure (an action value that a few
  annotated demonstrations never show the procedure that takes its other values taking: addition's write of
  a 0). Contested, that candidate would explain fewer demonstrations than level-wise training and lose
  (`selection.rank`), so it is not trained; asked for, it gets the narrowest call graph that fits every step."""
  stated = f"{int(np.sum(demos.strong))} of {len(demos.length)} demonstrations are annotated: "
  joint_graph = MODE_CALL_GRAPH["joint"]
  unfit = (None if "call_graph" in given or mode == "levelwise" else
           _unfit_step(joint_graph, demos, spec, numbers))
  if mode == "joint" and unfit:
    wider = call_graph.CALL_GRAPHS[:call_graph.CALL_GRAPHS.index(joint_graph)][::-1]  # calls, then all
    graph = next((g for g in wider if not _unfit_step(g, demos, spec, numbers)), "all")
    return [Candidate(mode, {"training": mode, "call_graph": graph})], [
        stated + f"joint training, as the settings given fix, with call graph {graph}: with the one the annotation "
        f"shows ({joint_graph}), {unfit}"]
  if mode:
    return [Candidate(mode, _mode_settings(mode, given))], [stated + f"{mode} training, as the settings given fix"]
  if unfit:
    return [Candidate("levelwise", _mode_settings("levelwise", given))], [
        stated + "level-wise training (the paper's); joint training is not tried: with the call graph the "
        f"annotation shows, {unfit}"]
  graphs = ("both with the call graph asked for" if "call_graph" in given else
            "every operation allowed in the first, the call graph the annotation shows in the second")
  return [Candidate(m, _mode_settings(m, given)) for m in ("levelwise", "joint")], [
      stated + f"level-wise training (the paper's) and joint training are both tried, {graphs}"]


def _unfit_step(graph: str, demos: Demonstration, spec: HierarchySpec, numbers) -> str | None:
  """Where call graph `graph` (one of call_graph.CALL_GRAPHS) leaves a step of demos to no procedure, in words
  (demonstrations named by numbers, else by their index); None where it fits every step."""
  allowed = call_graph.named(graph, demos, spec)
  unfit = call_graph.restricts(allowed) and call_graph.first_unfit(demos, spec, allowed)
  if not unfit:
    return None
  n, t, level = unfit
  return (f"no chain of calls fits demonstration {n if numbers is None else numbers[n]}'s step {t} (it breaks at "
          f"level {level})")


def _mode_settings(mode: str, given) -> dict:
  settings = {"training": mode}
  if "call_graph" not in given:
    settings["call_graph"] = MODE_CALL_GRAPH[mode]
  return settings


def _discovery_candidates(spec: HierarchySpec, demos: Demonstration, given,
                          mode: str) -> tuple[list[Candidate], list[str]]:
  """The candidates without annotation: where the segmentation starts from."""
  reason = f"no demonstration is annotated: {mode} training"
  if mode != "joint":
    return [Candidate(mode, {"training": mode})], [reason + ", as the settings given fix"]
  base = {"training": "joint"}
  if given & set(SEGMENTATION_SETTINGS):
    return [Candidate("joint", base)], [reason + "; the segmentation as the settings given fix"]
  if call_graph.restricts(spec.allowed_ops):
    return [Candidate("joint", base)], [reason + "; no segmentation: the hierarchy declares its call graph"]
  rules = {name: segmentation.read_rule(demos, name) for name in segmentation.RULES}
  applying = [name for name, rule in rules.items() if rule is not None]
  candidates = [Candidate(name, {**base, "segment_rule": name}) for name in applying]
  candidates.append(Candidate(UNSEGMENTED, {**base, "segment_iterations": 0, "split_rounds": 0}))
  words = [f"the {name} segmentation applies" if rules[name] else
           f"the {name} segmentation does not apply ({segmentation.UNSEGMENTED[name]})" for name in rules]
  return candidates, [reason + "; " + "; ".join(words) + "; " + (
      "it and starting unsegmented are both tried" if len(applying) == 1 else
      "each, and starting unsegmented, are tried" if applying else "training starts unsegmented")]
