"""The task interface: everything specific to one domain, so that data sets, training, evaluation and the
command-line tools work for any task that provides it.

A task bundles a pure, jittable environment (gymnax style: explicit state, static shapes), the hierarchy's
spec and its supervisor (the oracle that makes demonstrations), problem sampling by seed, the problem-file
line parser, the outcome line with its correctness rule, and the task's default training settings.

Problems are plain Python values (what a problem-file line parses to). Problems of similar size share a
*bucket* (an int the task chooses, e.g. a tape width): states of one bucket have one shape, so a batch of
them compiles once, and the oracle's step budget is fixed per bucket.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Protocol

import jax

from php_jax.hierarchy import HierarchySpec, Policy

Problem = Any


class Environment(Protocol):
  """A pure environment: states are pytrees with a `failed` [] bool field (an invalid action was taken)."""

  def observe(self, state) -> jax.Array:
    """[obs_dim] float32 observation of a state."""

  def step(self, state, action: jax.Array):
    """The state after elementary action [num_factors] int32; an invalid action only sets `failed`."""


@dataclasses.dataclass(frozen=True)
class TrainingDefaults:
  """A task's training set and test sets, and its overrides of the training settings (`config.TrainConfig`,
  each also overridable by the flag of the same name). A setting left None is TrainConfig's default.

  Attributes:
    num_demos: demonstrations in the training set.
    num_demos_fixed: whether the training set's size is fixed (then --num_demos may not change it).
    hidden: hidden layer sizes of every operation / termination network.
    tau_in_termination: per level, root first, whether ψ sees the counter τ.
    tau_limit: per level, root first, the networks see min(τ, limit) (None: no limit).
    min_capacity: per level, root first, the least counter capacity below the root (when calls can be
      longer than the annotated ones).
    test_lengths: problem sizes tested (one accuracy each); empty: one test set from the training
      distribution, reported as "accuracy".
    num_test: test problems per test set.
    iterations: Adam iterations per level.
    learning_rate: Adam's learning rate.
    training: where some demonstration is annotated, "levelwise" (one level at a time, the paper's) or "joint"
      (every level at once); without annotation a run trains jointly, the one mode that learns then.
    call_graph: which operations each procedure may take ("all", "calls" or "operations").
    segment_rule: the segmentation a joint run without annotation starts from ("loops" or "successors").
  """
  num_demos: int
  num_demos_fixed: bool
  hidden: tuple[int, ...]
  tau_in_termination: tuple[bool, ...]
  tau_limit: tuple[int | None, ...] | None = None
  min_capacity: tuple[int, ...] | None = None
  test_lengths: tuple[int, ...] = ()
  num_test: int = 100
  iterations: int | None = None
  learning_rate: float | None = None
  training: str | None = None
  call_graph: str | None = None
  segment_rule: str | None = None

  def overrides(self, annotated: bool = True) -> dict[str, Any]:
    """{TrainConfig field: value} of the settings this task sets for a training set with (or, annotated
    False, without) annotated demonstrations."""
    names = ("hidden", "tau_in_termination", "tau_limit", "min_capacity", "iterations", "learning_rate",
             "call_graph", "segment_rule") + (("training",) if annotated else ())
    return {name: getattr(self, name) for name in names if getattr(self, name) is not None}


@dataclasses.dataclass(frozen=True)
class Task:
  """One domain. See the module docstring; every callable is host-side Python unless it says jittable.

  Attributes:
    name: registry name (what --task takes).
    env: the environment (observe, step: jittable).
    spec: the hierarchy's levels, action factor sizes and observation size.
    oracle: the supervisor's hierarchy, a Policy of pure functions.
    training_problems: (seed, num) → the training set's problems.
    validation_problems: (seed, num) → about num problems from the training distribution.
    test_problems: (seed, num, length) → num problems of size `length` (None: the training distribution).
    bucket: problem → its bucket (int).
    make_states: (problems, bucket) → batched start states [B, ...] of that bucket's shape.
    step_budget: bucket → elementary steps the oracle needs at most on any problem of the bucket.
    parse_problem: one problem-file line's JSON object → problem; raises ValueError saying what is wrong (an
      unknown key included: see check_keys).
    outcome: (problem, final state of one episode) → (the output line's task fields, e.g. {"result": ...},
      whether the final state is the right answer).
    defaults: the training command's defaults.
    action_name: elementary action (a list of num_factors ints) → readable text for messages, e.g.
      "MOVE in1 RIGHT".
  """
  name: str
  env: Environment
  spec: HierarchySpec
  oracle: Policy
  training_problems: Callable[[int, int], list]
  validation_problems: Callable[[int, int], list]
  test_problems: Callable[[int, int, int | None], list]
  bucket: Callable[[Problem], int]
  make_states: Callable[[list, int], Any]
  step_budget: Callable[[int], int]
  parse_problem: Callable[[dict], Problem]
  outcome: Callable[[Problem, Any], tuple[dict, bool]]
  defaults: TrainingDefaults
  action_name: Callable[[list[int]], str] = str

  def states_and_budget(self, problems: list) -> tuple[Any, int]:
    """Start states of problems of any sizes on the largest one's bucket, and that bucket's step budget."""
    if not problems:
      raise ValueError("problems must list at least one problem")
    bucket = max(self.bucket(p) for p in problems)
    return self.make_states(problems, bucket), self.step_budget(bucket)
