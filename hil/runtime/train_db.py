"""The train DBC a scenario runs with (``can.dbc``): loaded, checked against the scenario, and its CAN FD frame
packing for the scenario's trains. Every runtime and tool loads the scenario's DBC through here."""
from __future__ import annotations

from trainhil_engine import Packing

from ecu_sim.codec import DbcMismatchError, TrainDb
from hil.scenario.loader import ScenarioError
from hil.scenario.model import Scenario


def load_train_db(sc: Scenario) -> TrainDb:
    """The scenario's DBC, checked against it (ScenarioError naming ``can.dbc`` when it does not fit)."""
    try:
        db = TrainDb.load(sc.can.dbc_path)
    except DbcMismatchError as exc:
        raise ScenarioError(f"can.dbc = {sc.can.dbc!r}: {exc}") from None
    check_train_db(sc, db)
    return db


def check_train_db(sc: Scenario, db: TrainDb) -> None:
    """A DBC with containers needs CAN FD buses, and the trains must fit the DBC's unit slots."""
    if db.containers and not sc.can.fd:
        names = ", ".join(c.name for c in db.containers[:3])
        raise ScenarioError(f"can.dbc = {sc.can.dbc!r} packs frames into CAN FD containers ({names}, ...): "
                            "set can.fd = true, or use train.dbc on classical CAN")
    if sc.trains.units > db.max_units:
        raise ScenarioError(f"trains.units = {sc.trains.units} exceeds the {db.max_units} unit slots of "
                            f"can.dbc = {sc.can.dbc!r}")


def bus_packing(sc: Scenario, db: TrainDb) -> Packing | None:
    """The frame packing of every train bus (containers cut to the train's units), None without containers."""
    return db.packing(sc.trains.units)
