"""marbler-jax: the Robotarium and MARBLER's multi-robot tasks, batched in JAX.

Submodules:
    physics      -- unicycle kinematics, actuator limits, arena checks (rps-exact).
    controllers  -- goal-to-velocity controllers and SI <-> unicycle maps.
    cbf          -- barrier certificates as fixed-iteration batched QP solvers.
    env          -- the batched env core (MARBLER's control loop); scenarios -- the tasks.

``make(name, **overrides)`` builds an env, ``registered()`` lists scenario names.
"""
from __future__ import annotations

import os

# jaxlib 0.10.2's CPU runtime can deadlock (the process idles forever inside an XLA call) in some
# training programs, e.g. QMIX_NS's vmapped GRU agents (hung 3 of 3 runs); with Eigen's intra-op
# thread pool off the same program completed 2 of 2 runs and neither env nor VDN throughput dropped.
# XLA reads XLA_FLAGS when the backend starts, so this applies unless JAX has already computed
# something. Set MARBLER_JAX_EIGEN_THREADS=1 (or choose the flag yourself in XLA_FLAGS) to opt out.
if "xla_cpu_multi_thread_eigen" not in os.environ.get("XLA_FLAGS", "") and \
        os.environ.get("MARBLER_JAX_EIGEN_THREADS") != "1":
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_multi_thread_eigen=false").strip()

import jax  # noqa: E402

from marbler_jax import cbf, controllers, physics  # noqa: E402

# Configuration dataclasses are hashable constants: register them as pytrees without leaves so
# they can be passed straight through jit/vmap boundaries.
jax.tree_util.register_static(physics.RobotariumParams)
jax.tree_util.register_static(cbf.Barrier)

from marbler_jax.registry import make, register, registered  # noqa: E402
from marbler_jax.adapters.gymnasium_env import register_gymnasium  # noqa: E402

register_gymnasium()

__version__ = "0.1.0"
__all__ = ["physics", "controllers", "cbf", "make", "register", "registered", "__version__"]
