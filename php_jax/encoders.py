"""How the networks see an observation: its fields, and the encoder a level's procedures share.

An observation is a vector of numbers (the demonstration files' form); its fields say what the numbers are, in
order, so that the shared encoder can treat each as what it is:
- `Categorical(n, ordered)`: a one-hot block of n entries (a Discrete value, one MultiDiscrete entry), seen
  through a learned embedding, with its ordinal value (index / (n − 1)) where the values are ordered (a row,
  a column);
- `Real(n)`: n numbers taken as they are (a Box of measurements, a MultiBinary);
- `Image(shape, codes)`: an H × W × C grid of integer codes, row-major (MiniGrid's cells are (object, colour,
  state) codes), each channel's code embedded, summed per cell, then two 3 × 3 convolutions, whose channels
  the observation's words (if it has any) scale and shift (FiLM, as BabyAI's models do: which cell matters
  hangs on the mission);
- `Tokens(length, vocab)`: a text as word ids in 1..vocab−1 (0 pads), each position's word embedded.
Between every two categorical fields of one size the encoder adds whether they are equal (and, both ordered,
which is less), and where there are at most MAX_PAIRED categorical fields, the product of every two fields'
embeddings: a decision that hangs on two factors together (the taxi's row and the passenger's landmark) is
then learned from the pairs the demonstrations show, not only from the exact combinations of every factor.

The JSON form (a hierarchy file's "observation", model.json): a list of objects, `{"categorical": 5,
"ordered": true}`, `{"real": 3}`, `{"image": [7, 7, 3], "codes": [11, 6, 3]}`, `{"tokens": 32, "vocab": 4096}`.
"""
from __future__ import annotations

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

DEFAULT_WIDTH = 64  # the encoder's width where the fields call for one and none is given
CHANNELS = (16, 32)  # the image convolutions' channels
EMBED = 8  # embedding width of every categorical field, image code and word
MAX_PAIRED = 16  # categorical fields beyond which their pairwise products are left out (their number grows as n²)
MAX_FIELD = 1 << 20  # the largest size a field may claim (a hierarchy file's or model.json's)


@dataclasses.dataclass(frozen=True)
class Categorical:
  size: int
  ordered: bool = False

  @property
  def entries(self) -> int:
    return self.size


@dataclasses.dataclass(frozen=True)
class Real:
  size: int

  @property
  def entries(self) -> int:
    return self.size


@dataclasses.dataclass(frozen=True)
class Image:
  shape: tuple[int, int, int]
  codes: tuple[int, ...]

  @property
  def entries(self) -> int:
    return int(np.prod(self.shape))


@dataclasses.dataclass(frozen=True)
class Tokens:
  length: int
  vocab: int

  @property
  def entries(self) -> int:
    return self.length


Field = Categorical | Real | Image | Tokens


def size(fields: tuple[Field, ...]) -> int:
  """How many numbers an observation of these fields has."""
  return sum(field.entries for field in fields)


def structured(fields: tuple[Field, ...] | None) -> bool:
  """Whether the fields say more than "numbers" (any field but Real): then the levels get an encoder."""
  return bool(fields) and any(not isinstance(field, Real) for field in fields)


def _positive(value, where: str, most: int = MAX_FIELD) -> int:
  if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= most:
    raise ValueError(f"{where} must be an integer in 1..{most}; got {str(value)[:80]}")
  return value


def from_json(value, where: str = '"observation"') -> tuple[Field, ...]:
  """Fields from their JSON form (the module's docstring); ValueError naming the field that is malformed."""
  if not (isinstance(value, list) and value):
    raise ValueError(f"{where} must be a non-empty list of fields; got {str(value)[:80]}")
  fields = []
  for i, obj in enumerate(value):
    at = f"{where}[{i}]"
    kinds = [k for k in ("categorical", "real", "image", "tokens") if isinstance(obj, dict) and k in obj]
    allowed = {"categorical": {"categorical", "ordered"}, "real": {"real"}, "image": {"image", "codes"},
               "tokens": {"tokens", "vocab"}}
    if len(kinds) != 1 or set(obj) - allowed[kinds[0]]:
      raise ValueError(f"{at} must be one of {{\"categorical\": n, \"ordered\": bool}}, {{\"real\": n}}, "
                       f"{{\"image\": [H, W, C], \"codes\": [...]}}, {{\"tokens\": n, \"vocab\": n}}; got {str(obj)[:80]}")
    kind = kinds[0]
    if kind == "categorical":
      ordered = obj.get("ordered", False)
      if not isinstance(ordered, bool):
        raise ValueError(f"{at}: \"ordered\" must be true or false; got {str(ordered)[:80]}")
      fields.append(Categorical(_positive(obj[kind], at), ordered))
    elif kind == "real":
      fields.append(Real(_positive(obj[kind], at)))
    elif kind == "image":
      shape, codes = obj[kind], obj.get("codes")
      if not (isinstance(shape, list) and len(shape) == 3):
        raise ValueError(f"{at}: \"image\" must be [height, width, channels]; got {str(shape)[:80]}")
      shape = tuple(_positive(n, f"{at}: \"image\"", 4096) for n in shape)
      if not (isinstance(codes, list) and len(codes) == shape[2]):
        raise ValueError(f"{at}: \"codes\" must give, per channel ({shape[2]}), how many codes it takes; got "
                         f"{str(codes)[:80]}")
      fields.append(Image(shape, tuple(_positive(n, f"{at}: \"codes\"", 65536) for n in codes)))
    else:
      fields.append(Tokens(_positive(obj[kind], at, 4096), _positive(obj.get("vocab"), f"{at}: \"vocab\"", 65536)))
  return tuple(fields)


def to_json(fields: tuple[Field, ...]) -> list[dict]:
  """The inverse of from_json."""
  out = []
  for field in fields:
    if isinstance(field, Categorical):
      out.append({"categorical": field.size, **({"ordered": True} if field.ordered else {})})
    elif isinstance(field, Real):
      out.append({"real": field.size})
    elif isinstance(field, Image):
      out.append({"image": list(field.shape), "codes": list(field.codes)})
    else:
      out.append({"tokens": field.length, "vocab": field.vocab})
  return out


class Encoder(nnx.Module):
  """One level's encoding of the observation, shared by its procedures' networks and computed once per
  observation: each field seen as what it is (the module's docstring), then a ReLU layer. [N, D] → [N, width].
  With fields of numbers only, that layer alone."""

  def __init__(self, fields: tuple[Field, ...], width: int, *, rngs: nnx.Rngs):
    self.fields = tuple(fields)
    self.width = width
    self.embeddings = nnx.List([
        nnx.Linear(f.size, EMBED, use_bias=False, rngs=rngs) if isinstance(f, Categorical)
        else nnx.List([nnx.Embed(n, EMBED, rngs=rngs) for n in f.codes]) if isinstance(f, Image)
        else nnx.Embed(f.vocab, EMBED, rngs=rngs) if isinstance(f, Tokens) else None
        for f in self.fields])
    self.convolutions = nnx.List([
        nnx.List([nnx.Conv(EMBED, n, (3, 3), rngs=rngs) for n in CHANNELS[:1]]
                 + [nnx.Conv(a, b, (3, 3), rngs=rngs) for a, b in zip(CHANNELS[:-1], CHANNELS[1:])])
        if isinstance(f, Image) else None for f in self.fields])
    text = sum(f.length * EMBED for f in self.fields if isinstance(f, Tokens))
    self.films = nnx.List([
        nnx.List([nnx.Linear(text, 2 * n, kernel_init=nnx.initializers.zeros, rngs=rngs) for n in CHANNELS])
        if isinstance(f, Image) and text else None for f in self.fields])
    features = self.features(jnp.zeros((1, size(self.fields)))).shape[-1]
    self.layer = nnx.Linear(features, width, rngs=rngs)

  def __call__(self, obs: jax.Array) -> jax.Array:
    return jax.nn.relu(self.layer(self.features(obs)))

  def features(self, obs: jax.Array) -> jax.Array:
    """[N, D] → [N, F]: every field's features, then the pairs' comparisons and products."""
    starts = np.cumsum([0] + [f.entries for f in self.fields])
    words = [self._words(field, embedding, obs[:, a:b]) for field, embedding, a, b
             in zip(self.fields, self.embeddings, starts[:-1], starts[1:]) if isinstance(field, Tokens)]
    text = jnp.concatenate(words, axis=1) if words else None
    parts, categorical = [], []
    for field, embedding, convolution, film, start in zip(self.fields, self.embeddings, self.convolutions,
                                                          self.films, starts):
      x = obs[:, start:start + field.entries]
      if isinstance(field, Real):
        parts.append(x)
      elif isinstance(field, Categorical):
        value = x @ jnp.arange(field.size, dtype=x.dtype)
        embedded = embedding(x)
        parts.append(embedded)
        if field.ordered and field.size > 1:
          parts.append(value[:, None] / (field.size - 1))
        categorical.append((field, x, value, embedded))
      elif isinstance(field, Image):
        codes = jnp.round(x).astype(jnp.int32).reshape(-1, *field.shape)
        cells = sum(embed(jnp.clip(codes[..., c], 0, n - 1)) for c, (embed, n) in
                    enumerate(zip(embedding, field.codes)))
        for layer, conv in enumerate(convolution):
          cells = conv(cells)
          if film is not None:  # the text scales and shifts each channel (FiLM), as BabyAI's models do
            scale, shift = jnp.split(film[layer](text)[:, None, None, :], 2, axis=-1)
            cells = cells * (1 + scale) + shift
          cells = jax.nn.relu(cells)
        parts.append(cells.reshape(cells.shape[0], -1))
      else:
        parts.append(self._words(field, embedding, x))
    for (a, xa, va, ea), (b, xb, vb, eb) in itertools.combinations(categorical, 2):
      if a.size == b.size:
        parts.append(jnp.sum(xa * xb, axis=1, keepdims=True))
        if a.ordered and b.ordered:
          parts.append(jnp.stack([va < vb, va > vb], axis=1).astype(obs.dtype))
      if len(categorical) <= MAX_PAIRED:
        parts.append(ea * eb)
    return jnp.concatenate(parts, axis=1)

  @staticmethod
  def _words(field: Tokens, embedding: nnx.Embed, x: jax.Array) -> jax.Array:
    """[N, length] word ids → [N, length · EMBED]: each position's word embedded, zeros where it pads."""
    words = jnp.clip(jnp.round(x).astype(jnp.int32), 0, field.vocab - 1)
    return (embedding(words) * (words > 0)[..., None]).reshape(words.shape[0], -1)


class History(nnx.Module):
  """A GRU over what was observed, for a level's procedures to remember: at step t it reads the level's
  encoding of o_t and the action a_{t−1} (one-hot per factor; zeros before the first), so its state depends on
  o_0..o_t and a_0..a_{t−1} alone, never on the call stack, and the E-step stays exact."""

  def __init__(self, features: int, action_sizes: tuple[int, ...], width: int, *, rngs: nnx.Rngs):
    self.action_sizes = tuple(action_sizes)
    self.width = width
    self.cell = nnx.GRUCell(features + sum(self.action_sizes), width, rngs=rngs)

  def initial(self, dtype=jnp.float32) -> jax.Array:
    """The state before the first observation: [width] zeros."""
    return jnp.zeros(self.width, dtype)

  def step(self, state: jax.Array, encoded: jax.Array, previous: jax.Array) -> jax.Array:
    """The state after reading one step: state [width], encoded [features], previous [F] int (−1: none)."""
    actions = [jax.nn.one_hot(previous[f], n, dtype=encoded.dtype) for f, n in enumerate(self.action_sizes)]
    state, _ = self.cell(state, jnp.concatenate([encoded, *actions]))
    return state

  def __call__(self, encoded: jax.Array, actions: jax.Array) -> jax.Array:
    """The state after each step of a demonstration: encoded [T+1, features], actions [T, F] → [T+1, width]."""
    previous = jnp.concatenate([jnp.full((1, actions.shape[1]), -1, actions.dtype), actions])

    def body(state, inputs):
      state = self.step(state, *inputs)
      return state, state

    _, states = jax.lax.scan(body, self.initial(encoded.dtype), (encoded, previous))
    return states
