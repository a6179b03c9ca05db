r"""Measures a Gymnasium environment and expert (Taxi's by default) through the documented commands: per seed,
record the expert's episodes, fit, act in 1,000 fresh episodes and decode 200 held-out annotated episodes
against the expert's stacks.

  python examples/taxi/measure.py --workdir=runs/taxi_measure --demos=100 --annotated=1,3,10 --seeds=1,2,3,4,5
  python examples/taxi/measure.py --workdir=runs/doorkey_measure --env=examples.doorkey.doorkey:make_env \
      --expert=examples.doorkey.doorkey:ThreePartExpert --hierarchy=examples/doorkey/doorkey.json

Seed s records its training episodes from seed 10000·s (each configuration's own demonstrations), the first
--annotated of them with the expert's stacks (--choose=suggest: those experiments.suggest chooses from their
actions), and fits with --seed=s; every run acts in the same 1,000 episodes (seeds 100000..100999) and decodes the
same 200 (seeds 500000..500199), none of which any training set holds. Each run acts twice in those episodes:
taking the policy's most likely choices ("success"), and drawing them with `act --sample` ("sampled", BabyAI's
protocol; a finished run measured before gets it on a rerun). --model=flat_lstm or flat_gru fits that flat
baseline on the same demonstrations instead. Finished runs are kept, so a rerun resumes (and stops, exit status 2,
at a finished run measured with another environment, expert, hierarchy file or fit flags); WORKDIR/rows.jsonl
holds the row of every finished run in WORKDIR (this invocation's and earlier ones'), and their table is printed
at the end.
"""
from __future__ import annotations

import argparse
import glob
import hashlib
import json
import os
import re
import subprocess
import sys

ENV, EXPERT, HIERARCHY = "examples.taxi.taxi:make_env", "examples.taxi.taxi:MaxqExpert", "examples/taxi/taxi.json"


def _run(*args: str) -> str:
  proc = subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True)
  if proc.returncode:
    raise SystemExit(f"{' '.join(args)} failed:\n{proc.stderr[-2000:]}")
  return proc.stdout


def _record(setup: argparse.Namespace, path: str, episodes: int, annotated: int, seed: int) -> None:
  if not os.path.exists(path):
    _run("experiments.record", f"--env={setup.env}", f"--expert={setup.expert}", f"--episodes={episodes}",
         f"--annotated={annotated}", f"--seed={seed}", f"--out={path}", f"--hierarchy={setup.hierarchy}")


def _record_chosen(setup: argparse.Namespace, path: str, episodes: int, annotated: int, seed: int) -> None:
  """Records the episodes with the expert's stacks on the `annotated` of them that experiments.suggest
  chooses from their actions alone, as a user would: record actions only, suggest, record again with
  --annotate."""
  if os.path.exists(path):
    return
  stem = path[:-len(".jsonl")]
  _record(setup, stem + "_actions.jsonl", episodes, 0, seed)
  _run("experiments.suggest", f"--demos={stem}_actions.jsonl", f"--hierarchy={setup.hierarchy}",
       f"--budget={annotated}", f"--out={stem}_suggested.jsonl")
  _run("experiments.record", f"--env={setup.env}", f"--expert={setup.expert}", f"--episodes={episodes}",
       f"--annotate={stem}_suggested.jsonl", f"--seed={seed}", f"--out={path}", f"--hierarchy={setup.hierarchy}")


def run_name(model: str, demos: int, annotated: int, choose: str, seed: int) -> str:
  """The name of one configuration's run of one seed in a workdir (with model "train": its training file's,
  which every model of the configuration shares)."""
  chosen = "" if choose == "first" else f"_{choose}"
  return f"{model}_d{demos}_a{annotated}{chosen}_s{seed}"


def measure(setup: argparse.Namespace, workdir: str, demos: int, annotated: int, seed: int, model: str,
            fit_flags: list[str]) -> dict:
  """One configuration and seed, run through record, fit, act and decode (setup: the environment, expert and
  hierarchy flags, and which episodes are annotated); returns its row."""
  name = run_name(model, demos, annotated, setup.choose, seed)
  run, done = os.path.join(workdir, name), os.path.join(workdir, name, "row.json")
  measured_with = _setup(setup, fit_flags)
  if os.path.exists(done):
    with open(done) as f:
      row = json.load(f)
    if "sampled" not in row and row.get("setup", measured_with) == measured_with:
      row["sampled"] = _act(setup, run, "--sample")
      _write_row(done, row)
    if row.get("setup", measured_with) != measured_with:
      print(f"{done} was measured with other settings ({row['setup']}); use another --workdir", file=sys.stderr)
      sys.exit(2)
    return row
  train = os.path.join(workdir, run_name("train", demos, annotated, setup.choose, seed) + ".jsonl")
  held = os.path.join(workdir, "held.jsonl")
  (_record if setup.choose == "first" else _record_chosen)(setup, train, demos, annotated, 10000 * seed)
  _record(setup, held, 200, 200, 500000)
  _run("experiments.fit", f"--demos={train}", f"--hierarchy={setup.hierarchy}", f"--workdir={run}", f"--seed={seed}",
       f"--model={model}", *fit_flags)
  row = {"model": model, "demos": demos, "annotated": annotated, "chosen": setup.choose, "seed": seed,
         "success": _act(setup, run), "sampled": _act(setup, run, "--sample")}
  if model == "php":
    row.update(decode(run, held))
  row["setup"] = measured_with
  _write_row(done, row)
  return row


def _act(setup: argparse.Namespace, run: str, *act_flags: str) -> float:
  """The success rate of the policy in `run` over the 1,000 acting episodes (their lines in
  run/episodes.jsonl, or episodes_sampled.jsonl with --sample)."""
  # Taxi ends an episode only on delivering the passenger, DoorKey only at the goal: there, ending is success.
  out = os.path.join(run, "episodes_sampled.jsonl" if act_flags else "episodes.jsonl")
  acted = _run("experiments.act", f"--policy={run}", f"--env={setup.env}", "--episodes=1000", "--seed=100000",
               "--num_envs=64", "--success=terminated", *act_flags, f"--out={out}")
  return float(re.search(r"success ([0-9.]+)", acted).group(1))


def _write_row(path: str, row: dict) -> None:
  with open(path + ".tmp", "w") as f:
    json.dump(row, f)
  os.replace(path + ".tmp", path)


def decode(run: str, held: str) -> dict:
  """The fitted hierarchy in `run` decoding the annotated episodes of `held` (experiments.decode): how many
  it replays, their log-likelihood per step, and per level the agreement with the expert's stacks (exact and
  up to renaming) and the call-boundary F1."""
  decoded = _run("experiments.decode", f"--policy={run}", f"--demos={held}",
                 f"--out={os.path.join(run, 'decoded.jsonl')}")
  row = {"held_out_replayed": int(re.search(r"(\d+)/\d+ replayed", decoded).group(1)),
         "held_out_log_likelihood": float(re.search(r"log-likelihood: ([-0-9.]+) per step", decoded).group(1))}
  for level, exact, renamed in re.findall(r"level (\d+): .* on ([0-9.]+) of annotated steps \(([0-9.]+)", decoded):
    row[f"level{level}"], row[f"level{level}_renamed"] = float(exact), float(renamed)
  for level, f1 in re.findall(r"level (\d+): .*call boundaries: F1 ([0-9.]+)", decoded):
    row[f"level{level}_boundary_f1"] = float(f1)
  return row


def _setup(setup: argparse.Namespace, fit_flags: list[str]) -> dict:
  """What a row was measured with besides its name: the environment, expert, hierarchy file (its sha256)
  and fit flags."""
  with open(setup.hierarchy, "rb") as f:
    digest = hashlib.sha256(f.read()).hexdigest()[:16]
  return {"env": setup.env, "expert": setup.expert, "hierarchy": f"{setup.hierarchy} {digest}",
          "fit_flags": list(fit_flags)}


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--workdir", required=True)
  parser.add_argument("--demos", default="100", help="comma-separated numbers of demonstrations")
  parser.add_argument("--annotated", default="3", help="comma-separated numbers annotated")
  parser.add_argument("--seeds", default="1,2,3,4,5")
  parser.add_argument("--model", default="php", choices=["php", "flat_lstm", "flat_gru"])
  parser.add_argument("--env", default=ENV, help="the environment's MODULE:ATTR (or Gymnasium id)")
  parser.add_argument("--expert", default=EXPERT, help="the expert's MODULE:ATTR")
  parser.add_argument("--hierarchy", default=HIERARCHY, help="the hierarchy file")
  parser.add_argument("--choose", default="first", choices=["first", "suggest"],
                      help="which episodes keep their stacks: the first --annotated, or those "
                      "experiments.suggest chooses")
  parser.add_argument("fit_flags", nargs="*", help="further experiments.fit flags, after --")
  args = parser.parse_args()
  os.makedirs(args.workdir, exist_ok=True)
  for demos in map(int, args.demos.split(",")):
    for annotated in map(int, args.annotated.split(",")):
      for seed in map(int, args.seeds.split(",")):
        print(json.dumps(measure(args, args.workdir, demos, annotated, seed, args.model, args.fit_flags)), flush=True)
  rows = []
  for done in glob.glob(os.path.join(args.workdir, "*", "row.json")):  # this and earlier invocations' runs
    with open(done) as f:
      rows.append(json.load(f))
  for row in rows:
    row.setdefault("chosen", "first")
  rows.sort(key=lambda r: (r["model"], r["demos"], r["annotated"], r["chosen"], r["seed"]))
  with open(os.path.join(args.workdir, "rows.jsonl.tmp"), "w") as f:
    f.writelines(json.dumps(row) + "\n" for row in rows)
  os.replace(os.path.join(args.workdir, "rows.jsonl.tmp"), os.path.join(args.workdir, "rows.jsonl"))
  print("| model | demos | annotated | chosen | success per seed | seeds ≥ 0.99 | sampled (--sample) per seed "
        "| level 1, 2 agreement (renamed), mean |")
  print("|---|---|---|---|---|---|---|---|")
  for key in sorted({(r["model"], r["demos"], r["annotated"], r["chosen"]) for r in rows}):
    group = [r for r in rows if (r["model"], r["demos"], r["annotated"], r["chosen"]) == key]
    agreement = ", ".join(f"{sum(r[f'level{k}_renamed'] for r in group) / len(group):.3f}"
                          for k in (1, 2) if f"level{k}_renamed" in group[0]) or "–"
    successes = " ".join(f"{r['success']:.3f}" for r in group)
    sampled = " ".join(f"{r['sampled']:.3f}" if "sampled" in r else "–" for r in group)
    sampled += f" ({sum(r.get('sampled', 0) >= 0.99 for r in group)}/{len(group)} ≥ 0.99)"
    print(f"| {key[0]} | {key[1]} | {key[2]} | {key[3]} | {successes} | "
          f"{sum(r['success'] >= 0.99 for r in group)}/{len(group)} | {sampled} | {agreement} |")


if __name__ == "__main__":
  main()
