"""MARBLER's five scenarios and JaxRobotarium's Discovery, Foraging and RWARE (bugs fixed), registered by
name; see :func:`marbler_jax.make`."""
from marbler_jax.scenarios.arctic_transport import ArcticTransport
from marbler_jax.scenarios.base import Scenario, ScenarioConfig
from marbler_jax.scenarios.discovery import Discovery
from marbler_jax.scenarios.foraging import Foraging
from marbler_jax.scenarios.material_transport import MaterialTransport
from marbler_jax.scenarios.predator_capture_prey import PredatorCapturePrey
from marbler_jax.scenarios.rware import Rware
from marbler_jax.scenarios.simple_navigation import SimpleNavigation
from marbler_jax.scenarios.warehouse import Warehouse

SCENARIOS: dict[str, type[Scenario]] = {
    cls.name: cls
    for cls in (SimpleNavigation, PredatorCapturePrey, Warehouse, MaterialTransport, ArcticTransport,
                Discovery, Foraging, Rware)
}

__all__ = ["Scenario", "ScenarioConfig", "SCENARIOS"]
