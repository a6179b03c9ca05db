r"""The E-step's operations on one small random lattice: posterior, k-best paths, tempered and differentiable
samples, KL divergence and cross-entropy between two posteriors, the online filter and forward mode.

  python examples/estep_operations.py
"""
import jax
import jax.numpy as jnp

import php_jax


def random_lattice(key, num_steps=6, num_procs=2, capacity=3):
  """Normalised log-probabilities: log_root [T, K], log_op, log_stop, log_cont [T, K, C]."""
  k1, k2, k3 = jax.random.split(key, 3)
  log_root = jax.nn.log_softmax(jax.random.normal(k1, (num_steps, num_procs)), axis=-1)
  log_op = jax.nn.log_sigmoid(2.0 * jax.random.normal(k2, (num_steps, num_procs, capacity)))
  z = jax.random.normal(k3, (num_steps, num_procs, capacity))
  return log_root, log_op, jax.nn.log_sigmoid(z), jax.nn.log_sigmoid(-z)


def main():
  p = php_jax.LatticeInputs(*random_lattice(jax.random.key(0)), length=5)  # step 5 is padding
  q = php_jax.LatticeInputs(*random_lattice(jax.random.key(1)), length=5)

  post = php_jax.forward_backward(*p)
  print(f"log P(xi) = {post.log_likelihood:.4f}; v[0] =\n{post.v[0]}")

  best = php_jax.top_k(3, *p)
  for i in range(3):
    print(f"top_k #{i}: procedures {best.procedures[i]}, counters {best.counters[i]}, log P = {best.log_prob[i]:.4f}")

  cold = php_jax.sample_posterior(jax.random.key(2), *p, temperature=0.3)
  print(f"sample at temperature 0.3: procedures {cold.procedures}, counters {cold.counters}")

  weights = jnp.arange(p.log_op.size, dtype=p.log_op.dtype).reshape(p.log_op.shape)
  grad = jax.grad(lambda op: jnp.sum(weights * php_jax.differentiable_sample(
      jax.random.key(3), p.log_root, op, p.log_stop, p.log_cont, p.length)))(p.log_op)
  print(f"straight-through sample: gradient w.r.t. log_op[0] =\n{grad[0]}")

  print(f"KL(p || q) = {php_jax.kl_divergence(p, q):.4f} nats, cross-entropy H(p, q) = "
        f"{php_jax.cross_entropy(p, q):.4f}, entropy H(p) = {php_jax.posterior_entropy(*p):.4f}")

  filt = php_jax.forward_filter(*p)
  print(f"forward_filter: log P(a_0..a_t) = {filt.log_prefix}; P(h_4, tau_4 | a_0..a_4) =\n{filt.filtered[4]}")

  log_likelihood = lambda op: php_jax.forward_backward(p.log_root, op, p.log_stop, p.log_cont, p.length).log_likelihood
  _, directional = jax.jvp(log_likelihood, (p.log_op,), (jnp.ones_like(p.log_op),))
  print(f"forward mode: d log P along all-ones d log_op = {directional:.4f} (= sum of v = {post.v.sum():.4f})")


if __name__ == "__main__":
  main()
