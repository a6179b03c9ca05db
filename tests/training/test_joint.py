"""Joint EG training of every level at once (--training=joint): it fits, and an interrupted run resumes to
the same result."""
import jax
import numpy as np
import pytest
from flax import nnx

from php_jax.envs import datasets, tasks
from php_jax.training import checkpoint, joint, train

NANOCRAFT = tasks.get("nanocraft")


def test_joint_training_lowers_the_loss_and_fits_annotated_demonstrations():
  batch = datasets.training_demos(NANOCRAFT, 1, 4, 4)
  config = train.TrainConfig(iterations=40, learning_rate=3e-2, hidden=(16,), eval_every=20, training="joint",
                             seed=1, length_buckets=1)
  rows = []
  hierarchy, report = joint.train_joint(NANOCRAFT.spec, batch, config, log=rows.append)
  losses = [loss for _, loss in report["losses"]]
  assert rows[0] == {"training": "joint", "capacity": report["capacity"]} and losses[-1] < 0.5 * losses[0]
  assert report["capacity"][1:] == [int(np.max(np.asarray(batch.counters)[..., level])) + 1 for level in (1, 2)]


@pytest.mark.slow
def test_interrupted_joint_training_resumes_to_the_same_result(tmp_path):
  batch = datasets.training_demos(NANOCRAFT, 2, 6, 2)
  config = train.TrainConfig(iterations=30, learning_rate=1e-2, hidden=(16,), eval_every=10, training="joint", seed=2)
  reference, _ = joint.train_joint(NANOCRAFT.spec, batch, config, log=lambda row: None)

  def stop_at_20(row):
    if row.get("iteration") == 20:
      raise KeyboardInterrupt
  path = str(tmp_path / checkpoint.TRAINING_DIR)
  with pytest.raises(KeyboardInterrupt):
    joint.train_joint(NANOCRAFT.spec, batch, config, log=stop_at_20, checkpoint_path=path)
  rows = []
  resumed, _ = joint.train_joint(NANOCRAFT.spec, batch, config, log=rows.append, checkpoint_path=path)
  # The checkpoint follows a row's logging: the run stopped at 20 resumes from 10's.
  assert rows[0]["resumed"] and rows[0]["iteration"] == 10 and [r.get("iteration") for r in rows[1:]] == [20, 30]
  for a, b in zip(jax.tree.leaves(nnx.state(reference, nnx.Param)), jax.tree.leaves(nnx.state(resumed, nnx.Param))):
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
  with pytest.raises(checkpoint.CheckpointError, match="other settings"):
    joint.train_joint(NANOCRAFT.spec, batch, train.TrainConfig(iterations=30, hidden=(16,), eval_every=10, seed=2),
                      log=lambda row: None, checkpoint_path=path)
