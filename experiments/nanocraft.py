r"""NanoCraft (paper §5.1): `experiments.train --task=nanocraft`, --num_demos random demonstrations.

  python -m experiments.nanocraft --workdir=runs/nc32 --num_demos=64 --num_strong=32 --seed=1
"""
from absl import app, flags

from experiments import train
from experiments.common import cli

flags.adopt_module_key_flags(train)

if __name__ == "__main__":
  flags.mark_flags_as_required(["workdir"])
  app.run(train.main_for("nanocraft"), flags_parser=cli.parse_flags)
