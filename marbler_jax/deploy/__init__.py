"""Deployment to the Robotarium: flat, JAX-free submission bundles (see :mod:`marbler_jax.deploy.bundle`)."""
