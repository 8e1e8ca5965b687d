"""The plant zoo: plant families simulated independently of ``pipeline.models.simulate``.

Each family (one module) is a physical plant written as its own ordinary differential
equations, with its nominal model YAML (the project's model format), DCS loops, actuators
and sensors; :mod:`tests.zoo.sim` integrates any of them (fine fixed-step RK4, a DCS that
scans once per second and acts on the previous scan, quantised OPs, a slow unmeasured
disturbance, sensor and input noise, historian snapshots) and injects one effect with a
known answer; :mod:`tests.zoo.trial` writes a trial as a user would have it: a historian
export, the model YAML and a discrepancy job YAML for ``plantdyn discrepancy``.

Families (:data:`FAMILIES`): ``heat_exchanger``, ``two_tanks``, ``blend``,
``valve_cooler``.  Nothing in ``pipeline/`` or ``flows/`` may import this package.
"""

from __future__ import annotations

from tests.zoo.blend import Blend
from tests.zoo.heat_exchanger import HeatExchanger
from tests.zoo.sim import ZOO_EFFECTS, Family, TrueEffect
from tests.zoo.two_tanks import TwoTanks
from tests.zoo.valve_cooler import ValveCooler

#: Every family by name (instances are stateless descriptions).
FAMILIES: dict[str, Family] = {
    f.name: f for f in (HeatExchanger(), TwoTanks(), Blend(), ValveCooler())
}

__all__ = ["FAMILIES", "ZOO_EFFECTS", "Family", "TrueEffect"]
