"""The library refuses what it cannot mean: one misuse of each kind, on concrete values outside jit, raises a
ValueError (GymError is one) whose message names the argument, before anything is compiled; lists where
arrays would do are taken. Tiny shapes, no rollout and at most a few compilations: the file runs in seconds."""
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx
from gymnasium import spaces

import php_jax
from php_jax import demos, executor
from php_jax.analysis import annotation_choice
from php_jax.data import call_tree
from php_jax.envs import addition, bubblesort, datasets, evaluation, gym, nanocraft, nanocraft_task, replay
from php_jax.hierarchy import HierarchySpec
from php_jax.inference import stack_lattice as sl
from php_jax.model import PHPHierarchy, PHPLevel, RootLSTM, RootMLP

T, K, C = 3, 2, 2
_RNG = np.random.default_rng(0)


def _f32(*shape):
  return jnp.asarray(_RNG.normal(size=shape), jnp.float32)


ROOT, OP, STOP, CONT = _f32(T, K), _f32(T, K, C), _f32(T, K, C), _f32(T, K, C)
INPUTS = php_jax.LatticeInputs(ROOT, OP, STOP, CONT, T)
ANNOTATION = jnp.array([0, 1, 0])
KEY = jax.random.key(0)
# d = 2 levels: K_0 = 1, C_0 = 2, K_1 = 2, C_1 = 2.
STACK = sl.StackInputs((_f32(T, 1, 2, 2),), _f32(T, 2, 2), (_f32(T, 1, 2), _f32(T, 2, 2)),
                       (_f32(T, 1, 2), _f32(T, 2, 2)), T)
STACK_ANNOTATION = jnp.array([[0, 0], [0, 1], [0, 0]])
SPEC = HierarchySpec("probe", (("root",), ("a", "b")), (3,), 4)
TASK = nanocraft_task.TASK
STATES = nanocraft_task.make_states(TASK.training_problems(0, 2))
# Two recorded episodes of 2 steps (a stand-in for rollout_batch's result: nothing runs).
ROLLOUTS = executor.Rollout(None, np.zeros((2, 3, 4), np.float32), np.zeros((2, 2, 1), np.int32),
                            np.zeros((2, 2, 2), np.int32), np.zeros((2, 2, 2), np.int32), np.array([2, 2]),
                            np.array([True, True]), np.array([True, True]), np.zeros((2, 1), np.int32))
BATCH = demos.Demonstration(np.zeros((2, 3, 4), np.float32), np.zeros((2, 2, 1), np.int32),
                            np.zeros((2, 2, 2), np.int32), np.zeros((2, 2, 2), np.int32), np.array([2, 2]),
                            np.array([False, False]))
STACK_2D = np.array([[0, 0], [0, 0], [0, 1]]), np.array([[0, 0], [0, 1], [1, 0]])


def _rngs():
  return nnx.Rngs(0)


MISUSES = [
    # two-level E-step: the lattice's arrays
    ("None for an array", lambda: php_jax.forward_backward(None, OP, STOP, CONT), "log_root must be a float array"),
    ("boolean array", lambda: php_jax.forward_backward(ROOT, OP > 0, STOP, CONT), "log_op must be a float array"),
    ("integer arrays", lambda: php_jax.viterbi(*(jnp.zeros(jnp.shape(x), jnp.int32) for x in INPUTS[:4])),
     "log_root must be a float array .* got dtype int32"),
    ("a batch axis", lambda: php_jax.forward_backward(ROOT, jnp.stack([OP, OP]), STOP, CONT),
     r"log_op must be \[T, K, C\]; got shape \(2, 3, 2, 2\)"),
    ("T differs", lambda: php_jax.forward_filter(ROOT, OP, STOP, CONT[:1]), "log_cont must have log_op's shape"),
    ("K differs", lambda: php_jax.forward_backward(ROOT[:, :1], OP, STOP, CONT), r"log_root must be \[T, K\]"),
    ("K = 0", lambda: php_jax.forward_backward(jnp.zeros((T, 0)), *(jnp.zeros((T, 0, C)),) * 3),
     "T, K and C must be ≥ 1; log_op has shape"),
    ("NaN", lambda: php_jax.forward_backward(ROOT, OP.at[1, 0, 1].set(jnp.nan), STOP, CONT),
     r"log_op contains NaN at index \(1, 0, 1\)"),
    ("+inf", lambda: php_jax.posterior_entropy(ROOT, OP, STOP.at[0, 1, 0].set(jnp.inf), CONT),
     r"log_stop contains \+inf at index \(0, 1, 0\)"),
    # length, temperature, key, k, method
    ("length 0", lambda: php_jax.forward_backward(INPUTS._replace(length=0)), "length must be in 1..T = 1..3; got 0"),
    ("length T+1", lambda: php_jax.viterbi(INPUTS._replace(length=T + 1)), "length must be in 1..T"),
    ("length float array", lambda: php_jax.forward_backward(INPUTS._replace(length=jnp.array(2.0))),
     "length must be an integer"),
    ("length a string", lambda: php_jax.forward_backward(INPUTS._replace(length="2")), "length must be an integer"),
    ("temperature NaN", lambda: php_jax.sample_posterior(KEY, INPUTS, temperature=float("nan")),
     "temperature must be a finite number > 0; got nan"),
    ("temperature None", lambda: php_jax.sample_posterior(KEY, INPUTS, temperature=None),
     "temperature must be a finite number > 0; got None"),
    ("temperature a string", lambda: php_jax.differentiable_sample(KEY, INPUTS, temperature="1"),
     "temperature must be a finite number > 0"),
    ("key None", lambda: php_jax.sample_posterior(None, INPUTS), "key must be one PRNG key .*got None"),
    ("key an int", lambda: php_jax.differentiable_sample(0, INPUTS), "key must be one PRNG key"),
    ("a batch of keys", lambda: php_jax.sample_posterior(jax.random.split(KEY), INPUTS),
     r"key must be one PRNG key.*shape \(2,\)"),
    ("k None", lambda: php_jax.top_k(None, INPUTS), "k must be an int ≥ 1; got None"),
    ("k -3", lambda: php_jax.top_k(-3, INPUTS), "k must be an int ≥ 1; got -3"),
    ("method unknown", lambda: php_jax.differentiable_sample(KEY, INPUTS, method="gumbel"), "method must be"),
    # annotations
    ("procedures [T, 1]", lambda: php_jax.forward_backward(INPUTS, procedures=jnp.zeros((T, 1), jnp.int32)),
     r"procedures must have shape \(3,\)"),
    ("procedures bool", lambda: php_jax.forward_backward(INPUTS, procedures=jnp.array([True, False, True])),
     "procedures must be an integer array"),
    ("counters -2", lambda: php_jax.viterbi(INPUTS, counters=jnp.array([0, -2, 0])),
     r"counters\[1\] = -2 is outside −1..C−1"),
    ("procedure 2**40", lambda: php_jax.complete_log_likelihood(INPUTS, np.array([0, 2 ** 40, 0]), ANNOTATION),
     r"procedure\[1\] = 1099511627776 is outside"),
    ("counter None", lambda: php_jax.complete_log_likelihood(INPUTS, ANNOTATION, None),
     "counter must be an integer array"),
    # the other two-level functions
    ("annotate: log_op rank 2", lambda: php_jax.annotate(OP[:, :, 0], ANNOTATION, ANNOTATION),
     r"log_op must be \[T, K, C\]"),
    ("annotate: log_op None", lambda: php_jax.annotate(None, ANNOTATION, ANNOTATION), "log_op must be a float array"),
    ("top_level: K = 2", lambda: php_jax.top_level(STOP), r"log_stop must be \[T, 1, C\]"),
    ("top_level: length T+1", lambda: php_jax.top_level(STOP[:, :1], T + 1), "length must be in 1..T"),
    ("max_marginal_path: an array", lambda: php_jax.max_marginal_path(OP), "posterior must be a LatticePosterior"),
    ("max_marginal_path: length 0", lambda: php_jax.max_marginal_path(php_jax.LatticePosterior(0.0, OP, OP), 0),
     "length must be in 1..T"),
    ("kl_divergence: a 3-tuple", lambda: php_jax.kl_divergence(INPUTS[:3], INPUTS),
     "p must be a LatticeInputs .*got a tuple of 3"),
    ("cross_entropy: None", lambda: php_jax.cross_entropy(INPUTS, None), "q must be a LatticeInputs .*got None"),
    ("TwoLevelLattice: a StackInputs", lambda: php_jax.TwoLevelLattice(STACK), "inputs must be a LatticeInputs"),
    # the stack lattice
    ("stack: None", lambda: sl.forward_backward(None), "inputs must be a StackInputs .*got None"),
    ("stack: a LatticeInputs", lambda: php_jax.StackLattice(INPUTS), "inputs must be a StackInputs"),
    ("stack: log_call an array", lambda: sl.viterbi(STACK._replace(log_call=STACK.log_call[0])),
     "log_call must be a tuple of arrays"),
    ("stack: log_act None", lambda: sl.forward_backward(STACK._replace(log_act=None)),
     "log_act must be a float array"),
    ("stack: boolean log_act", lambda: sl.log_likelihood(STACK._replace(log_act=STACK.log_act > 0)),
     "log_act must be a float array .*got dtype bool"),
    ("stack: C = 0", lambda: sl.forward_backward(STACK._replace(log_stop=(jnp.zeros((T, 1, 0)), STACK.log_stop[1]))),
     r"log_stop\[0\] must be \[T, K, C\] with T, K, C ≥ 1"),
    ("stack: NaN", lambda: sl.top_k(2, STACK._replace(log_act=STACK.log_act.at[0, 1, 0].set(jnp.nan))),
     r"log_act contains NaN at index \(0, 1, 0\)"),
    ("stack: +inf", lambda: sl.posterior_entropy(STACK._replace(log_call=(STACK.log_call[0].at[2].set(jnp.inf),))),
     r"log_call\[0\] contains \+inf at index \(2, 0, 0, 0\)"),
    ("stack: procedures [T]", lambda: sl.forward_backward(STACK, procedures=jnp.zeros(T, jnp.int32)),
     r"procedures must have shape \(3, 2\)"),
    ("stack: counters == C_0", lambda: sl.viterbi(STACK, counters=STACK_ANNOTATION.at[2, 0].set(2)),
     r"counters\[2, 0\] = 2 is outside −1..C_0−1"),
    ("stack: key None", lambda: sl.sample_posterior(None, STACK), "key must be one PRNG key"),
    ("stack: k 1.5", lambda: sl.top_k(1.5, STACK), "k must be an int ≥ 1; got 1.5"),
    ("stack: q None", lambda: sl.cross_entropy(STACK, None), "q must be a StackInputs"),
    # models and hierarchies
    ("PHPLevel: num_procs 0", lambda: PHPLevel(0, 4, (3,), (8,), rngs=_rngs()), "num_procs must be an integer ≥ 1"),
    ("PHPLevel: num_procs 2.5", lambda: PHPLevel(2.5, 4, (3,), (8,), rngs=_rngs()), "num_procs must be an integer"),
    ("PHPLevel: obs_dim -1", lambda: PHPLevel(2, -1, (3,), (8,), rngs=_rngs()), "obs_dim must be an integer ≥ 0"),
    ("PHPLevel: op_sizes ()", lambda: PHPLevel(2, 4, (), (8,), rngs=_rngs()), "op_sizes must name at least one"),
    ("PHPLevel: hidden 0", lambda: PHPLevel(2, 4, (3,), (0,), rngs=_rngs()), r"hidden\[0\] must be an integer ≥ 1"),
    ("PHPLevel: hidden an int", lambda: PHPLevel(2, 4, (3,), 8, rngs=_rngs()), "hidden must be a tuple of integers"),
    ("PHPLevel: tau_limit -1", lambda: PHPLevel(2, 4, (3,), (8,), tau_limit=-1, rngs=_rngs()),
     "tau_limit must be an integer ≥ 0"),
    ("RootMLP: no children", lambda: RootMLP(4, 0, (8,), rngs=_rngs()), "num_children must be an integer ≥ 1"),
    ("RootLSTM: hidden 0", lambda: RootLSTM(4, 2, 0, rngs=_rngs()), "hidden must be an integer ≥ 1"),
    ("PHPHierarchy: spec None", lambda: PHPHierarchy(None, (8,), rngs=_rngs()), "spec must be a HierarchySpec"),
    ("HierarchySpec: two roots", lambda: HierarchySpec("x", (("r", "s"), ("a",)), (3,), 4),
     "levels: the root level has one procedure"),
    ("HierarchySpec: an empty level", lambda: HierarchySpec("x", (("r",), ()), (3,), 4),
     "levels must be a non-empty tuple of non-empty tuples"),
    ("HierarchySpec: action size 0", lambda: HierarchySpec("x", (("r",), ("a",)), (0,), 4),
     r"action_sizes\[0\] must be an integer ≥ 1"),
    ("HierarchySpec: obs_dim -1", lambda: HierarchySpec("x", (("r",), ("a",)), (3,), -1), "obs_dim must be"),
    # the executor and demonstrations
    ("rollout_batch: max_steps 0",
     lambda: executor.rollout_batch(TASK.oracle, TASK.spec, TASK.env, STATES, jax.random.split(KEY, 2), 0),
     "max_steps must be an integer ≥ 1"),
    ("rollout_batch: max_steps 2.5",
     lambda: executor.rollout_batch(TASK.oracle, TASK.spec, TASK.env, STATES, jax.random.split(KEY, 2), 2.5),
     "max_steps must be an integer"),
    ("rollout_batch: 3 keys, 2 states",
     lambda: executor.rollout_batch(TASK.oracle, TASK.spec, TASK.env, STATES, jax.random.split(KEY, 3), 10),
     r"states.grid must have a leading batch axis of B = 3, the number of keys"),
    ("rollout_batch: one key", lambda: executor.rollout_batch(TASK.oracle, TASK.spec, TASK.env, STATES, KEY, 10),
     r"keys must be a batch \[B\] of PRNG keys"),
    ("from_rollouts: not recorded", lambda: demos.from_rollouts(ROLLOUTS._replace(observations=None), True),
     "rollouts must be recorded"),
    ("from_rollouts: strong [3] for 2", lambda: demos.from_rollouts(ROLLOUTS, [True, False, True]),
     r"strong must be one bool or \[B\] = \[2\] bools"),
    ("validate: spec None", lambda: demos.validate(BATCH, None), "spec must be a HierarchySpec"),
    ("replay: chunk 0", lambda: replay.replay(TASK.oracle, TASK.spec, BATCH, chunk=0),
     "chunk must be a positive integer; got 0"),
    ("replay: chunk 2.5", lambda: replay.replay(TASK.oracle, TASK.spec, BATCH, chunk=2.5),
     "chunk must be a positive integer; got 2.5"),
    # Gymnasium helpers
    ("flatten_observation: out of Discrete", lambda: gym.flatten_observation(spaces.Discrete(3), 5),
     r"observation 5 is not in Discrete\(3\)"),
    ("flatten_observation: Box shape", lambda: gym.flatten_observation(spaces.Box(0, 1, (2,)), [0.1, 0.2, 0.3]),
     r"observation must have the shape \(2,\)"),
    ("flatten_observation: Dict key missing",
     lambda: gym.flatten_observation(spaces.Dict({"a": spaces.Discrete(2)}), {"b": 0}), "observation must be a dict"),
    ("action_factors: out of Discrete", lambda: gym.action_factors(spaces.Discrete(3), 3),
     "action 3 is not in the action space"),
    ("action_factors: MultiDiscrete entries", lambda: gym.action_factors(spaces.MultiDiscrete([2, 3]), [1]),
     r"action \[1\] is not in the action space"),
    ("env_actions: 1-D", lambda: gym.env_actions(spaces.Discrete(3), np.array([0, 1])),
     r"factors must be \[M, 1\] integers"),
    ("env_actions: out of range", lambda: gym.env_actions(spaces.Discrete(3), np.array([[3]])),
     r"factors\[0, 0\] = 3 is outside 0..2"),
    # call trees, data sets, annotation choice, tasks
    ("calls: 1-D stacks", lambda: call_tree.calls(np.zeros(3, int), np.zeros(3, int)),
     r"procedures must be an integer array \[T, d\]"),
    ("calls: shapes differ", lambda: call_tree.calls(STACK_2D[0], STACK_2D[1][:2]), "counters must have procedures'"),
    ("calls: length 0", lambda: call_tree.calls(*STACK_2D, 0), "length must be an integer in 1..T = 1..3; got 0"),
    ("strong_mask: num_strong 2.5", lambda: datasets.strong_mask(4, 2.5, 0), "num_strong must be an integer ≥ 0"),
    ("suggest: budget -1", lambda: annotation_choice.suggest(BATCH, -1), "budget must be an integer ≥ 0"),
    ("suggest: certainty_of", lambda: annotation_choice.suggest(BATCH, 1, certainty_of=np.ones(5)),
     r"certainty_of must be \[B\] = \[2\]"),
    ("nanocraft: x 1.5", lambda: nanocraft.make_problem(1.5, 1, 2, 2), "x must be an integer; got 1.5"),
    ("nanocraft: w True", lambda: nanocraft.make_problem(1, 1, True, 2), "w must be an integer; got True"),
    ("addition: numbers", lambda: addition.make_problem(12, 34), "a and b must be decimal strings"),
    ("bubblesort: digit 1.7", lambda: bubblesort.make_problem([3, 1.7]), "an array must hold integer digits"),
    ("bubblesort: width 3.5", lambda: bubblesort.make_problem([3, 1], 3.5), "width must be an integer; got 3.5"),
    ("states_and_budget: no problems", lambda: TASK.states_and_budget([]), "problems must list at least one"),
    ("accuracy: no problems", lambda: evaluation.accuracy(TASK, "oracle", []), "accuracy needs at least one problem"),
]


@pytest.mark.parametrize("call, message", [pytest.param(call, message, id=name) for name, call, message in MISUSES])
def test_a_misuse_is_refused_in_one_line_naming_the_argument(call, message):
  with pytest.raises(ValueError, match=message) as refused:
    call()
  assert "\n" not in str(refused.value)


def test_lists_and_numpy_values_are_taken_where_arrays_would_do():
  """Nested lists of floats for the lattice (converted as jnp.asarray converts them), a 0-d integer array for
  k, NumPy integers for sizes."""
  listed = php_jax.forward_backward(ROOT.tolist(), OP.tolist(), STOP.tolist(), CONT.tolist(), 2)
  np.testing.assert_array_equal(listed.v, php_jax.forward_backward(ROOT, OP, STOP, CONT, 2).v)
  stacked = sl.log_likelihood(STACK._replace(log_cont=[x.tolist() for x in STACK.log_cont]))
  np.testing.assert_array_equal(stacked, sl.log_likelihood(STACK))
  assert php_jax.inference.lattice_inputs.check_k(jnp.array(2)) == 2
  assert datasets.strong_mask(4, np.int64(2), 0).sum() == 2
  assert gym.action_factors(spaces.Discrete(3, start=1), 3) == [2]
  assert nanocraft.make_problem(*np.array([1, 1, 2, 2])).spec.tolist() == [1, 1, 2, 2]


def test_under_jit_the_value_checks_are_skipped_not_broken():
  """A traced NaN or length is not looked at: tracing works and the result is what the values give."""
  nan_op = OP.at[1, 0, 1].set(jnp.nan)
  traced = jax.jit(lambda op, n: php_jax.forward_backward(ROOT, op, STOP, CONT, n).log_likelihood)(nan_op, 2)
  assert np.isnan(traced)
  with pytest.raises(ValueError, match=re.escape("log_op contains NaN at index (1, 0, 1)")):
    php_jax.forward_backward(ROOT, nan_op, STOP, CONT, 2)
  assert jax.jit(php_jax.top_level)(STOP[:, :1], 2).shape == (T, 1, C)
