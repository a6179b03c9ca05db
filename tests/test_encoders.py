"""Observation fields and the encoders that read them: the JSON form, what each field contributes, a model
with fields saved and loaded, the fields of Gymnasium spaces (MiniGrid's included), and an environment seen
only as an image and a text, learned end to end through record, fit --env and act."""
from __future__ import annotations

import json

import gymnasium
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx
from gymnasium import spaces

from php_jax import encoders
from php_jax.data import demo_files
from php_jax.envs import gym
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy
from php_jax.training import checkpoint
from tests import processes

FIELDS_JSON = [{"categorical": 5, "ordered": True}, {"categorical": 5, "ordered": True}, {"categorical": 5},
               {"categorical": 4}, {"real": 2}, {"image": [3, 4, 2], "codes": [4, 3]}, {"tokens": 4, "vocab": 50}]
FIELDS = encoders.from_json(FIELDS_JSON)


def observation(rng: np.random.Generator, batch: int) -> np.ndarray:
  """[batch, size(FIELDS)] random observations of FIELDS: one-hot categories, numbers, codes, word ids."""
  parts = []
  for field in FIELDS:
    if isinstance(field, encoders.Categorical):
      parts.append(np.eye(field.size)[rng.integers(field.size, size=batch)])
    elif isinstance(field, encoders.Real):
      parts.append(rng.normal(size=(batch, field.size)))
    elif isinstance(field, encoders.Image):
      codes = np.stack([rng.integers(n, size=(batch, *field.shape[:2])) for n in field.codes], -1)
      parts.append(codes.reshape(batch, -1))
    else:
      parts.append(rng.integers(field.vocab, size=(batch, field.length)))
  return np.concatenate(parts, axis=1).astype(np.float32)


def test_fields_round_trip_through_json_and_take_their_entries():
  assert encoders.to_json(FIELDS) == FIELDS_JSON
  assert encoders.size(FIELDS) == 5 + 5 + 5 + 4 + 2 + 24 + 4
  assert encoders.structured(FIELDS) and not encoders.structured((encoders.Real(3),)) and not encoders.structured(None)


@pytest.mark.parametrize("value, message", [
    ([], "must be a non-empty list"),
    ([{"categorical": 0}], r"\[0\] must be an integer in 1\.\."),
    ([{"real": 2}, {"categorical": 3, "ordered": 1}], r"\[1\]: \"ordered\" must be true or false"),
    ([{"categorical": 3, "real": 2}], r"\[0\] must be one of"),
    ([{"categorical": 3, "size": 2}], r"\[0\] must be one of"),
    ([{"image": [7, 7], "codes": [11, 6]}], r"\[0\]: \"image\" must be \[height, width, channels\]"),
    ([{"image": [7, 7, 3], "codes": [11, 6]}], r"\[0\]: \"codes\" must give, per channel \(3\)"),
    ([{"tokens": 4}], r"\[0\]: \"vocab\" must be an integer"),
])
def test_malformed_fields_are_refused_naming_the_field(value, message):
  with pytest.raises(ValueError, match=message):
    encoders.from_json(value)


def test_numbers_alone_are_one_relu_layer():
  encoder = encoders.Encoder((encoders.Real(6),), 5, rngs=nnx.Rngs(0))
  x = jnp.asarray(np.random.default_rng(0).normal(size=(3, 6)), jnp.float32)
  np.testing.assert_allclose(encoder(x), jnp.maximum(x @ encoder.layer.kernel[...] + encoder.layer.bias[...], 0))


def test_each_field_is_seen_as_what_it_is():
  encoder = encoders.Encoder(FIELDS, 16, rngs=nnx.Rngs(0))
  x = observation(np.random.default_rng(1), 6)
  assert encoder(jnp.asarray(x)).shape == (6, 16)
  # a padding word (id 0) contributes nothing: changing its embedding leaves every feature as it was
  x[:, -2:] = 0
  before = np.asarray(encoder.features(jnp.asarray(x)))
  encoder.embeddings[-1].embedding[...] = encoder.embeddings[-1].embedding[...].at[0].set(100.0)
  np.testing.assert_array_equal(np.asarray(encoder.features(jnp.asarray(x))), before)
  # the comparisons between the two ordered categories of size 5: equal, less, greater
  y = observation(np.random.default_rng(2), 3)
  y[:, :10] = 0
  for row, (a, b) in enumerate([(2, 2), (1, 3), (4, 0)]):
    y[row, a], y[row, 5 + b] = 1, 1
  features = np.asarray(encoder.features(jnp.asarray(y)))
  comparisons = [c for c in range(features.shape[1]) if set(np.unique(features[:, c])) <= {0.0, 1.0}]
  wanted = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
  assert any(np.array_equal(features[:, comparisons[i:i + 3]], wanted) for i in range(len(comparisons) - 2))


def test_a_hierarchy_with_fields_is_saved_and_loaded_with_them(tmp_path):
  spec = HierarchySpec("fields", (("root",), ("a", "b")), (3,), encoders.size(FIELDS), observation=FIELDS)
  model = PHPHierarchy(spec, hidden=(8,), rngs=nnx.Rngs(3))
  assert model.levels[0].trunk.width == encoders.DEFAULT_WIDTH
  checkpoint.save_hierarchy(str(tmp_path), "fields", model, (8,))
  architecture = json.loads((tmp_path / checkpoint.ARCHITECTURE_FILE).read_text())
  assert architecture["spec"]["observation"] == FIELDS_JSON and architecture["trunk"] == encoders.DEFAULT_WIDTH
  _, loaded = checkpoint.load_policy(str(tmp_path))
  assert loaded.spec == spec
  x, tau = jnp.asarray(observation(np.random.default_rng(4), 5)), jnp.arange(3.0)
  for mine, theirs in zip(model.levels, loaded.levels):
    np.testing.assert_array_equal(theirs.termination_logits(theirs.encode(x), tau),
                                  mine.termination_logits(mine.encode(x), tau))


def test_the_hierarchy_file_gives_fields_and_they_must_fit_the_demonstrations(tmp_path):
  hierarchy = {"levels": [["root"], ["a", "b"]], "action_sizes": [2], "observation": [{"categorical": 3},
                                                                                         {"real": 1}]}
  path = tmp_path / "h.json"
  path.write_text(json.dumps(hierarchy))
  spec = demo_files.read_hierarchy(str(path)).spec
  assert spec.observation == (encoders.Categorical(3), encoders.Real(1))
  demos = tmp_path / "d.jsonl"
  demos.write_text(json.dumps({"observations": [[1, 0, 0, 0.5, 7], [0, 1, 0, 0.5, 7]], "actions": [[0]]}) + "\n")
  with pytest.raises(demo_files.DemoFileError, match="its fields take 4 numbers where observations have 5"):
    demo_files.read_demonstrations(str(demos), spec)
  path.write_text(json.dumps({**hierarchy, "observation": [{"categorical": 3, "ordered": "yes"}]}))
  with pytest.raises(demo_files.DemoFileError, match=r'"observation"\[0\]: "ordered" must be true or false'):
    demo_files.read_hierarchy(str(path))
  path.write_text(json.dumps({**hierarchy, "observes": [None, {"a": [0]}]}))
  with pytest.raises(demo_files.DemoFileError, match="observes: procedures that see different observation entries"):
    demo_files.read_hierarchy(str(path))


def test_gymnasium_spaces_give_their_fields_minigrids_mission_included():
  space = spaces.Dict({"cell": spaces.Discrete(3), "grid": spaces.MultiDiscrete([5, 4]),
                       "view": spaces.Box(0, 10, (2, 2, 2), np.uint8), "speed": spaces.Box(-1, 1, (3,)),
                       "said": spaces.Text(40, charset="abcdefgh ")})
  fields = gym.observation_fields(space)
  assert fields == (encoders.Categorical(3), encoders.Categorical(5, True), encoders.Categorical(4, True),
                    encoders.Tokens(32, 4096), encoders.Real(3), encoders.Image((2, 2, 2), (11, 11)))
  value = {"cell": 1, "grid": np.array([2, 3]), "view": np.ones((2, 2, 2), np.uint8), "speed": np.zeros(3, np.float32),
           "said": "Bad cafe, bad!"}
  flat = gym.flatten_observation(space, value)
  assert flat.shape == (gym.observation_size(space),) == (encoders.size(fields),)
  said = flat[3 + 9:3 + 9 + 32]
  assert said[0] == said[2] and said[0] != said[1] and np.all(said[:3] >= 1) and not np.any(said[3:])
  with pytest.raises(gym.GymError, match=r"observation\['said'\] has 33 words; php_jax reads at most 32"):
    gym.flatten_observation(space, {**value, "said": "a " * 33})
  minigrid = pytest.importorskip("minigrid")
  del minigrid
  env = gymnasium.make("BabyAI-GoToLocal-v0")
  assert encoders.to_json(gym.observation_fields(env.observation_space)) == [
      {"categorical": 4}, {"image": [7, 7, 3], "codes": [256, 256, 256]}, {"tokens": 32, "vocab": 4096}]
  obs, _ = env.reset(seed=0)
  assert gym.flatten_observation(env.observation_space, obs).shape == (183,)


LENGTH = 6
LEFT, RIGHT = 0, 1
HIERARCHY = {"levels": [["root"], ["walk_left", "walk_right"]], "action_sizes": [2]}


class SeenCorridor(gymnasium.Env):
  """Walk to the end of a corridor the mission names ("walk left", "walk to the right"), seen only as an
  image (the agent's cell has code 1, the others 0) and the mission's words."""

  observation_space = spaces.Dict({"image": spaces.Box(0, 1, (1, LENGTH, 1), np.uint8),
                                   "mission": spaces.Text(30, charset="abcdefghijklmnopqrstuvwxyz ")})
  action_space = spaces.Discrete(2)
  MISSIONS = ("walk left", "walk right", "go to the left", "go to the right")

  def reset(self, *, seed=None, options=None):
    super().reset(seed=seed)
    self.mission = self.MISSIONS[int(self.np_random.integers(4))]
    self.position = int(self.np_random.integers(1, LENGTH - 1))
    return self._observation(), {}

  def step(self, action):
    self.position = int(np.clip(self.position + (1 if action == RIGHT else -1), 0, LENGTH - 1))
    done = self.position == (LENGTH - 1 if self.mission.endswith("right") else 0)
    return self._observation(), -1.0, done, False, {"is_success": True} if done else {}

  def _observation(self):
    image = np.zeros((1, LENGTH, 1), np.uint8)
    image[0, self.position, 0] = 1
    return {"image": image, "mission": self.mission}


def make_seen_corridor() -> gymnasium.Env:
  return gymnasium.wrappers.TimeLimit(SeenCorridor(), 20)


class SeenCorridorExpert:
  """Root calls walk_left or walk_right, which steps to the end: stack [[0, 0], [side, steps so far]]."""

  def __init__(self, env):
    self.steps = 0

  def reset(self, observation, info):
    self.steps = 0

  def act(self, observation, info):
    side = int(observation["mission"].endswith("right"))
    self.steps += 1
    return (RIGHT if side else LEFT), [[0, 0], [side, self.steps - 1]]


def test_an_environment_seen_as_an_image_and_words_is_learned_end_to_end(tmp_path):
  lines = gym.record(make_seen_corridor(), SeenCorridorExpert(None), episodes=24, seed=0, annotate=4)
  run = processes.fit_recorded(tmp_path, HIERARCHY, lines, "--env=tests.test_encoders:make_seen_corridor",
                               "--iterations=150", "--eval_every=50", "--hidden=16", "--learning_rate=0.01")
  architecture = json.loads((run / checkpoint.ARCHITECTURE_FILE).read_text())
  assert architecture["spec"]["observation"] == [{"image": [1, LENGTH, 1], "codes": [2]},
                                                 {"tokens": 32, "vocab": 4096}]
  assert architecture["end_given"]  # recorded in an environment: it ends the episodes
  _, policy = checkpoint.load_policy(str(run))
  assert policy.memory == encoders.DEFAULT_WIDTH  # fit's default where the observation holds an image
  episodes = gym.act(policy, gym.vector_env(make_seen_corridor, 4), 40, seed=100)
  assert all(e["success"] for e in episodes), episodes
  # the flat LSTM reads the same encoder, and is its own memory
  flat = processes.fit_recorded(tmp_path / "flat", HIERARCHY, lines, "--env=tests.test_encoders:make_seen_corridor",
                                "--model=flat_lstm", "--lstm_hidden=16", "--iterations=20", "--eval_every=10")
  _, lstm = checkpoint.load_policy(str(flat))
  assert lstm.cell_kind == "lstm" and lstm.hidden == 16  # --lstm_hidden: --flat_hidden's older name
  assert lstm.encoder.fields == encoders.from_json(architecture["spec"]["observation"])
  assert len(gym.act(lstm, gym.vector_env(make_seen_corridor, 2), 2, seed=100)) == 2
