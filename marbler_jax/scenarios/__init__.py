"""MARBLER's scenarios (and ours), registered by name; see :func:`marbler_jax.make`."""
from marbler_jax.scenarios.arctic_transport import ArcticTransport
from marbler_jax.scenarios.base import Scenario, ScenarioConfig
from marbler_jax.scenarios.material_transport import MaterialTransport
from marbler_jax.scenarios.predator_capture_prey import PredatorCapturePrey
from marbler_jax.scenarios.simple_navigation import SimpleNavigation
from marbler_jax.scenarios.warehouse import Warehouse

SCENARIOS: dict[str, type[Scenario]] = {
    cls.name: cls
    for cls in (SimpleNavigation, PredatorCapturePrey, Warehouse, MaterialTransport, ArcticTransport)
}

__all__ = ["Scenario", "ScenarioConfig", "SCENARIOS"]
