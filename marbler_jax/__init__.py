"""marbler-jax: the Robotarium and MARBLER's multi-robot tasks, batched in JAX.

Submodules:
    physics      -- unicycle kinematics, actuator limits, arena checks (rps-exact).
    controllers  -- goal-to-velocity controllers and SI <-> unicycle maps.
    cbf          -- barrier certificates as fixed-iteration batched QP solvers.
    env          -- the batched env core (MARBLER's control loop); scenarios -- the tasks.

``make(name, **overrides)`` builds an env, ``registered()`` lists scenario names.
"""
from __future__ import annotations

import jax

from marbler_jax import cbf, controllers, physics

# Configuration dataclasses are hashable constants: register them as pytrees without leaves so
# they can be passed straight through jit/vmap boundaries.
jax.tree_util.register_static(physics.RobotariumParams)
jax.tree_util.register_static(cbf.Barrier)

from marbler_jax.registry import make, register, registered  # noqa: E402
from marbler_jax.adapters.gymnasium_env import register_gymnasium  # noqa: E402

register_gymnasium()

__version__ = "0.1.0"
__all__ = ["physics", "controllers", "cbf", "make", "register", "registered", "__version__"]
