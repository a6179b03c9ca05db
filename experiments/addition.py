r"""Long-hand addition (paper §5.2): `experiments.train --task=addition`, 160 traces (16 per length 1..10).

  python -m experiments.addition --workdir=runs/add10 --num_strong=10 --seed=1
"""
from absl import app, flags

from experiments import train
from experiments.common import cli

flags.adopt_module_key_flags(train)

if __name__ == "__main__":
  flags.mark_flags_as_required(["workdir"])
  app.run(train.main_for("addition"), flags_parser=cli.parse_flags)
