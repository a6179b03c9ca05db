r"""CompILE (Kipf et al., ICML 2019, "CompILE: Compositional Imitation Learning and Execution") as an outside
peer for hierarchy discovery from actions alone: trains its segmentation model on a demonstration file and
scores its segmentation of held-out annotated demonstrations against the supervisor's calls at one level.

  python -m experiments.compile_peer --compile_dir=COMPILE --hierarchy=H.json --demos=TRAIN.jsonl \
      --held_out=HELD.jsonl --out=OUT.json [--seed=1 --iterations=800]

--compile_dir is a copy of https://github.com/tkipf/compile (PyTorch; tested at commit b88b174): a checkout
holding modules.py and utils.py, or a git directory (bare, or a checkout's .git) whose HEAD is read at run
time. Nothing of CompILE's code is copied into this repository: its `modules.CompILE` (the LSTM segmentation
encoder with Gumbel-softmax boundaries b and per-segment latents z, and the MLP decoder) and
`utils.get_losses` (the negative ELBO: reconstruction, KL on z, Poisson prior on b) are imported from there
unchanged, and this command only feeds them. Needs torch (`pip install -e ".[peer]"`: torch 2.13.0, a CPU build).

How the files are fed to CompILE, as its train.py feeds its toy sequences: each demonstration's elementary
actions become one symbol per step (the action's index + 1; several action factors are numbered jointly),
then CompILE's end symbol 0; a training batch is padded with 0 after the end. Its decoder reconstructs each
segment's symbols from the segment's latent alone; with --observations, the encoder also sees each step's
observation (standardized, through a linear layer added to the symbol's embedding; CompILE's public code has
symbols only). Segmentation (CompILE in eval mode): segment i covers the steps from the previous boundary up
to its boundary's arg-max (clamped to be non-decreasing and within the demonstration, as CompILE's
`get_reconstruction_accuracy` does); its label is the arg-max of its latent (--latent_dist=concrete) or the
k-means cluster (k = the level's number of procedures) of its latent mean (gaussian).

Scored against every held-out demonstration whose stack is known at the levels down to --level:
  boundary_precision, _recall, _f1   a call boundary at --level is a step t ≥ 1 where a new call starts
                                     there (a level above it resumed); predicted: every step t ≥ 1 where a
                                     non-empty segment starts; exact steps, pooled over demonstrations
  boundary_*_within_1                the same with a predicted boundary counting when one step off (each true
                                     boundary matched once)
  accuracy_up_to_renaming            the fraction of steps whose segment label, under the best one-to-one
                                     renaming of labels to the level's procedures (over all steps pooled),
                                     equals the supervisor's procedure
  position_accuracy_up_to_renaming   the same with each segment labelled by its position (0, 1, ...) in the
                                     demonstration instead of its latent
Prints one JSON line with these numbers (and the settings) and writes it to --out.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import types

import numpy as np

from php_jax.data.agreement import boundary_scores, boundary_steps, known_call_boundaries, label_agreement

# --- CompILE's segments as labelled steps: pure functions of numpy arrays (the tests check them). ---


def segments_from_boundaries(boundaries, num_steps: int) -> np.ndarray:
  """[num_steps] int: each step's segment index, from the segments' end boundaries (CompILE's: segment i
  covers the steps from the previous boundary up to, not including, boundary i; made non-decreasing and at
  most num_steps, the last one num_steps). Empty segments keep their index unused."""
  ends = np.minimum(np.maximum.accumulate(np.asarray(boundaries, int)), num_steps)
  ends[-1] = num_steps
  segment = np.zeros(num_steps, int)
  start = 0
  for i, end in enumerate(ends):
    segment[start:end] = i
    start = max(start, end)
  return segment


def kmeans(points, k: int, seed: int, iterations: int = 100) -> np.ndarray:
  """[N] cluster of each point [N, D] by k-means (k-means++ start, seeded); k is capped at N."""
  points = np.asarray(points, np.float64)
  rng, k = np.random.default_rng(seed), min(k, len(points))
  centers = [points[rng.integers(len(points))]]
  for _ in range(1, k):
    distance = np.min(((points[:, None] - np.array(centers)[None]) ** 2).sum(-1), axis=1)
    total = distance.sum()
    pick = rng.choice(len(points), p=distance / total) if total > 0 else rng.integers(len(points))
    centers.append(points[pick])
  centers = np.array(centers)
  labels = np.zeros(len(points), int)
  for _ in range(iterations):
    labels = ((points[:, None] - centers[None]) ** 2).sum(-1).argmin(1)
    new = np.array([points[labels == c].mean(0) if np.any(labels == c) else centers[c] for c in range(k)])
    if np.allclose(new, centers):
      break
    centers = new
  return labels


def action_symbols(actions, action_sizes) -> np.ndarray:
  """[T] int: each step's action [T, factors] numbered jointly (mixed radix, first factor most significant)
  plus 1, so that 0 stays CompILE's end and padding symbol."""
  actions = np.asarray(actions, int).reshape(len(actions), len(action_sizes))
  return np.ravel_multi_index(tuple(actions.T), tuple(action_sizes)) + 1 if len(actions) else np.zeros(0, int)


# --- CompILE, imported from its own code. ---


def load_compile(compile_dir: str):
  """(CompILE's `modules`, its `utils`, the commit or None) from a checkout with modules.py and utils.py,
  or from a git directory's HEAD (copied to a temporary directory). Raises ValueError naming the flag."""
  commit = None
  if os.path.isfile(os.path.join(compile_dir, "modules.py")):
    source = compile_dir
    found = subprocess.run(["git", "-C", compile_dir, "rev-parse", "--show-toplevel", "HEAD"], capture_output=True,
                           text=True)
    top, head = (found.stdout.split() + [None, None])[:2] if found.returncode == 0 else (None, None)
    commit = head if top and os.path.realpath(top) == os.path.realpath(compile_dir) else None  # not a repo above
  else:
    found = subprocess.run(["git", "--git-dir", compile_dir, "rev-parse", "HEAD"], capture_output=True, text=True)
    if found.returncode != 0:
      raise ValueError(f"--compile_dir={compile_dir}: neither a checkout holding modules.py nor a git directory")
    commit, source = found.stdout.strip(), tempfile.mkdtemp(prefix="compile_")
    for name in ("modules.py", "utils.py"):
      shown = subprocess.run(["git", "--git-dir", compile_dir, "show", f"HEAD:{name}"], capture_output=True)
      if shown.returncode != 0:
        raise ValueError(f"--compile_dir={compile_dir}: HEAD has no {name}")
      with open(os.path.join(source, name), "wb") as f:
        f.write(shown.stdout)
  import importlib.util  # pylint: disable=import-outside-toplevel

  def module(name: str, as_name: str):
    spec = importlib.util.spec_from_file_location(as_name, os.path.join(source, f"{name}.py"))
    loaded = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(loaded)
    return loaded

  saved = sys.modules.get("utils")
  try:
    utils = module("utils", "compile_utils")
    sys.modules["utils"] = utils  # modules.py says `import utils`
    modules = module("modules", "compile_modules")
  finally:
    if saved is None:
      sys.modules.pop("utils", None)
    else:
      sys.modules["utils"] = saved
    if source != compile_dir:
      shutil.rmtree(source, ignore_errors=True)
  for owner, names in ((modules, ("CompILE",)), (utils, ("get_losses", "get_reconstruction_accuracy"))):
    missing = [n for n in names if not hasattr(owner, n)]
    if missing:
      raise ValueError(f"--compile_dir={compile_dir}: {owner.__name__} lacks {', '.join(missing)}")
  return modules, utils, commit


def _sequences(batch, spec, mean=None, std=None):
  """Per demonstration: (symbols [T+1] ending in 0, standardized observations [T+1, D])."""
  obs = np.asarray(batch.observations, np.float64)
  lengths = np.asarray(batch.length)
  if mean is None:
    steps = np.concatenate([obs[b, :n + 1] for b, n in enumerate(lengths)])
    mean, std = steps.mean(0), steps.std(0) + 1e-6
  out = []
  for b, n in enumerate(lengths):
    symbols = np.concatenate([action_symbols(np.asarray(batch.actions)[b, :n], spec.action_sizes), [0]])
    out.append((symbols, (obs[b, :n + 1] - mean) / std))
  return out, mean, std


def _observation_embedding(torch, num_symbols: int, hidden_dim: int, obs_dim: int):
  """A stand-in for CompILE's nn.Embedding that adds a linear map of each step's observation (set in
  `.observations` [B, T, D] before each forward pass) to the symbol's embedding."""

  class ObservationEmbedding(torch.nn.Module):

    def __init__(self):
      super().__init__()
      self.symbols = torch.nn.Embedding(num_symbols, hidden_dim)
      self.obs = torch.nn.Linear(obs_dim, hidden_dim)
      self.observations = None

    def forward(self, inputs):
      return self.symbols(inputs) + self.obs(self.observations)

  return ObservationEmbedding()


def _pad(torch, sequences, indices):
  symbols = torch.nn.utils.rnn.pad_sequence([torch.as_tensor(sequences[i][0]) for i in indices], batch_first=True)
  obs = torch.nn.utils.rnn.pad_sequence([torch.as_tensor(sequences[i][1], dtype=torch.float32) for i in indices],
                                        batch_first=True)
  lengths = torch.tensor([len(sequences[i][0]) for i in indices])
  return symbols, obs, lengths


def train_and_segment(settings, train_batch, held_batch, spec, log=print) -> dict:
  """Trains CompILE on train_batch and segments held_batch: {"segments": per held-out demonstration [T]
  segment index, "labels": per demonstration {segment index: its latent's arg-max, or latent mean},
  "train_nll", "held_out_reconstruction_accuracy", "train_seconds"}."""
  import torch  # pylint: disable=import-outside-toplevel
  modules, utils, _ = settings.compile
  torch.manual_seed(settings.seed)
  torch.set_num_threads(settings.threads)
  rng = np.random.default_rng(settings.seed)
  train, mean, std = _sequences(train_batch, spec)
  held, _, _ = _sequences(held_batch, spec, mean, std)
  num_symbols = int(np.prod(spec.action_sizes))
  args = types.SimpleNamespace(num_symbols=num_symbols, num_segments=settings.num_segments,
                               latent_dim=settings.latent_dim, latent_dist=settings.latent_dist)
  model = modules.CompILE(input_dim=num_symbols + 1, hidden_dim=settings.hidden_dim, latent_dim=settings.latent_dim,
                          max_num_segments=settings.num_segments, temp_b=settings.temp_b, temp_z=settings.temp_z,
                          latent_dist=settings.latent_dist)
  if settings.observations:
    model.embed = _observation_embedding(torch, num_symbols + 1, settings.hidden_dim, train[0][1].shape[1])
  optimizer = torch.optim.Adam(model.parameters(), lr=settings.learning_rate)

  def forward(symbols, obs, lengths):
    if settings.observations:
      model.embed.observations = obs
    return model.forward(symbols, lengths)

  start, nll = time.time(), float("nan")
  for step in range(settings.iterations):
    indices = (np.arange(len(train)) if settings.batch_size >= len(train)
               else rng.choice(len(train), settings.batch_size, replace=False))
    symbols, obs, lengths = _pad(torch, train, indices)
    model.train()
    optimizer.zero_grad()
    loss, nll_t, kl_z, kl_b = utils.get_losses(symbols, forward(symbols, obs, lengths), args, beta_b=settings.beta_b,
                                                beta_z=settings.beta_z, prior_rate=settings.prior_rate)
    loss.backward()
    optimizer.step()
    nll = nll_t.item()
    if settings.log_every and (step % settings.log_every == 0 or step == settings.iterations - 1):
      log(f"step {step}: loss {loss.item():.4f}, nll {nll:.4f}, kl_z {kl_z.item():.4f}, kl_b {kl_b.item():.4f} "
          f"({time.time() - start:.1f}s)")
  train_seconds = time.time() - start

  model.eval()
  segments, labels = [None] * len(held), [None] * len(held)
  correct = 0.0
  by_length = {}
  for i, (symbols, _) in enumerate(held):
    by_length.setdefault(len(symbols), []).append(i)
  with torch.no_grad():
    for length, indices in sorted(by_length.items()):  # equal lengths: no padding
      symbols, obs, lengths = _pad(torch, held, indices)
      outputs = forward(symbols, obs, lengths)
      _, _, _, all_b, all_z = outputs
      accuracy, _ = utils.get_reconstruction_accuracy(symbols, outputs, args)
      correct += float(accuracy) * len(indices)
      ends = torch.stack([b.argmax(-1) for b in all_b["samples"]], 1).numpy()  # [B, K]
      if settings.latent_dist == "concrete":
        latents = torch.stack([z.argmax(-1) for z in all_z["logits"]], 1).numpy()  # [B, K]
      else:
        latents = torch.stack([z[:, :settings.latent_dim] for z in all_z["logits"]], 1).numpy()  # [B, K, L]
      for row, i in enumerate(indices):
        segments[i] = segments_from_boundaries(ends[row], length - 1)
        labels[i] = {int(s): latents[row, s] for s in np.unique(segments[i])}
  return {"segments": segments, "labels": labels, "train_nll": nll, "train_seconds": train_seconds,
          "held_out_reconstruction_accuracy": correct / len(held)}


def score(held_batch, spec, level: int, segments, labels, latent_dist: str, seed: int) -> dict:
  """The metrics of the module docstring from train_and_segment's segments and labels."""
  procs, lengths = np.asarray(held_batch.procedures), np.asarray(held_batch.length)
  scored = known_call_boundaries(held_batch.procedures, held_batch.counters, lengths, level)
  true_b = [boundaries for _, boundaries in scored]
  predicted_b = [boundary_steps(np.diff(segments[b], prepend=-1) != 0) for b, _ in scored]
  exact, near = boundary_scores(true_b, predicted_b), boundary_scores(true_b, predicted_b, tolerance=1)
  keys = [(b, s) for b, _ in scored for s in sorted(labels[b])]
  if latent_dist == "concrete":
    label_of = {key: int(labels[key[0]][key[1]]) for key in keys}
  else:
    clusters = kmeans(np.stack([labels[b][s] for b, s in keys]), len(spec.levels[level]), seed)
    label_of = dict(zip(keys, clusters.tolist()))
  truth = np.concatenate([procs[b, :lengths[b], level] for b, _ in scored])
  predicted = np.concatenate([[label_of[b, s] for s in segments[b]] for b, _ in scored])
  position = np.concatenate([segments[b] for b, _ in scored])
  accuracy, renaming = label_agreement(truth, predicted)
  position_accuracy, _ = label_agreement(truth, position)
  names = spec.levels[level]
  return {"held_out_scored": len(scored), "boundary_precision": exact["precision"],
          "boundary_recall": exact["recall"], "boundary_f1": exact["f1"],
          "boundary_precision_within_1": near["precision"], "boundary_recall_within_1": near["recall"],
          "boundary_f1_within_1": near["f1"], "true_boundaries": exact["true"],
          "predicted_boundaries": exact["predicted"], "accuracy_up_to_renaming": accuracy,
          "renaming": {f"z{k}": names[v] for k, v in sorted(renaming.items())},
          "position_accuracy_up_to_renaming": position_accuracy}


# --- The command. Its flags are defined only when it runs as a command, so that the tests can import this
# module beside other commands that define flags of the same names. ---


def _define_flags():
  from absl import flags  # pylint: disable=import-outside-toplevel
  d = types.SimpleNamespace()
  d.compile_dir = flags.DEFINE_string("compile_dir", None, "CompILE's code: a checkout of github.com/tkipf/compile "
                                      "(modules.py, utils.py) or its git directory (HEAD is read).")
  d.hierarchy = flags.DEFINE_string("hierarchy", None, "Hierarchy file (JSON) of the demonstrations.")
  d.demos = flags.DEFINE_string("demos", None, "Training demonstrations, JSON lines or a binary set (stacks, if any, "
                                "unused).")
  d.held_out = flags.DEFINE_string("held_out", None, "Held-out demonstrations annotated with their stack.")
  d.out = flags.DEFINE_string("out", None, "Output JSON file (the printed line).")
  d.level = flags.DEFINE_integer("level", 1, "Level of the supervisor's calls to score against.", lower_bound=1)
  d.seed = flags.DEFINE_integer("seed", 1, "Seed of the initialisation, Gumbel/Gaussian noise, minibatches and "
                                "k-means.", lower_bound=0)
  d.iterations = flags.DEFINE_integer("iterations", 800, "Training iterations (Adam steps). CompILE's default is "
                                      "100 batches of 512 sequences; 800 full batches of 64 see as many.",
                                      lower_bound=0)
  d.batch_size = flags.DEFINE_integer("batch_size", 64, "Demonstrations per step (all when at least as many).",
                                      lower_bound=1)
  d.learning_rate = flags.DEFINE_float("learning_rate", 1e-2, "Adam's learning rate (CompILE's default).")
  d.hidden_dim = flags.DEFINE_integer("hidden_dim", 64, "Hidden units (CompILE's default).", lower_bound=1)
  d.num_segments = flags.DEFINE_integer("num_segments", None, "Segments per demonstration. Default: the number of "
                                        "procedures at --level (6 for NanoCraft, whose root calls each once).",
                                        lower_bound=1)
  d.latent_dist = flags.DEFINE_enum("latent_dist", "concrete", ["concrete", "gaussian"], "CompILE's latents z: "
                                    "concrete (discrete, a segment's label is its arg-max) or gaussian (labels by "
                                    "k-means of the means).")
  d.latent_dim = flags.DEFINE_integer("latent_dim", None, "Size of z. Default: the number of procedures at --level "
                                      "for concrete, 32 (CompILE's default) for gaussian.", lower_bound=1)
  d.temp_b = flags.DEFINE_float("temp_b", 1.0, "Gumbel-softmax temperature of the boundaries (CompILE's default).")
  d.temp_z = flags.DEFINE_float("temp_z", 1.0, "Temperature of concrete latents (CompILE's default).")
  d.beta_b = flags.DEFINE_float("beta_b", 0.1, "Weight of the boundaries' KL term (CompILE's default).")
  d.beta_z = flags.DEFINE_float("beta_z", 0.1, "Weight of the latents' KL term (CompILE's default).")
  d.prior_rate = flags.DEFINE_float("prior_rate", 3.0, "Poisson rate of the segment-length prior (CompILE's default).")
  d.observations = flags.DEFINE_boolean("observations", False, "Also feed each step's observation to the encoder "
                                        "(CompILE's public code reads symbols only).")
  d.threads = flags.DEFINE_integer("threads", 1, "torch's CPU threads.", lower_bound=1)
  d.log_every = flags.DEFINE_integer("log_every", 100, "Print the losses every this many iterations (0: never).",
                                     lower_bound=0)
  return d


def main(argv, defined):
  from experiments.common import cli  # pylint: disable=import-outside-toplevel
  from php_jax.data import demo_files, files  # pylint: disable=import-outside-toplevel
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  cli.exit_on_interrupt(f"--out={defined.out.value} not written")
  settings = types.SimpleNamespace(**{name: flag.value for name, flag in vars(defined).items()})
  try:
    cli.check_outputs({"out": settings.out}, {"demos": settings.demos, "held_out": settings.held_out,
                                              "hierarchy": settings.hierarchy})
    spec = demo_files.read_hierarchy(settings.hierarchy).spec
    if settings.level >= spec.num_levels:
      raise ValueError(f"--level must be below {spec.num_levels} (the hierarchy's levels); got {settings.level}")
    train_batch, spec = demo_files.read_demonstrations(settings.demos, spec)
    held_batch, _ = demo_files.read_demonstrations(settings.held_out, spec)
    if not known_call_boundaries(held_batch.procedures, held_batch.counters, held_batch.length, settings.level):
      raise ValueError(f"--held_out={settings.held_out}: no demonstration carries its stack down to level "
                       f"{settings.level}")
    try:
      import torch  # noqa: F401  pylint: disable=import-outside-toplevel,unused-import
    except ImportError:
      raise ValueError('CompILE needs torch: pip install -e ".[peer]"') from None
    settings.compile = load_compile(settings.compile_dir)
  except (OSError, ValueError) as e:  # DemoFileError is one
    cli.fail(str(e))
  num_procs = len(spec.levels[settings.level])
  settings.num_segments = settings.num_segments or num_procs
  settings.latent_dim = settings.latent_dim or (num_procs if settings.latent_dist == "concrete" else 32)
  found = train_and_segment(settings, train_batch, held_batch, spec)
  metrics = score(held_batch, spec, settings.level, found["segments"], found["labels"], settings.latent_dist,
                  settings.seed)
  row = {"model": "compile", "compile_commit": settings.compile[2], "seed": settings.seed,
         "iterations": settings.iterations, "num_segments": settings.num_segments,
         "latent_dist": settings.latent_dist, "latent_dim": settings.latent_dim,
         "observations": settings.observations, "level": settings.level,
         "train_demos": int(len(train_batch.length)), "held_out_demos": int(len(held_batch.length)), **metrics,
         "held_out_reconstruction_accuracy": found["held_out_reconstruction_accuracy"],
         "train_nll": found["train_nll"], "train_seconds": round(found["train_seconds"], 1)}
  line = json.dumps(row)
  with cli.output_errors("out", settings.out):
    files.write_atomically(settings.out, (line + "\n").encode())
  print(line)


if __name__ == "__main__":
  from absl import app, flags  # pylint: disable=ungrouped-imports

  from experiments.common import cli
  DEFINED = _define_flags()
  flags.mark_flags_as_required(["compile_dir", "hierarchy", "demos", "held_out", "out"])
  app.run(lambda argv: main(argv, DEFINED), flags_parser=cli.parse_flags)
