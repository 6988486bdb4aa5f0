"""The radio gateway: a cangw-style routing table that bridges frames between adjacent train buses.

A route (src_bus, src_id) -> (dst_bus, dst_id, link) forwards the payload unchanged over a named
``RadioLink``; only the CAN ID is remapped, so the payload's E2E protection (CRC over the data ID
and the bytes) stays valid end to end.

Link ends and positions: a link is named ``"a>b"`` (1-based train numbers: ``"1>2"`` carries
train 1's frames, bus index 0, to train 2, bus index 1); its reverse is ``"b>a"``. The gateway
remembers, per link, the last position carried by a frame it forwarded over that link: the
position of the link's sender end, on the sender's bus. A frame is judged with its own position
(or, if it carries none, the last one of its end) against the last position of the other end,
i.e. the last position seen on the reverse link. Positions are taken from the frames heard on
the source bus, before the radio, as each end's gateway knows its own train's position locally.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ecu_sim.codec import TrainDb
from hil.scenario.layout import TrainLayout
from hil.radio.link import RadioLink
from hil.scenario.model import RadioConfig


_RADIO_SEED_TAG = 0x5241_4449  # "RADI": keeps link seeds apart from other spawn() children of the same rng


@dataclass(frozen=True)
class RadioIds:
    """The frame IDs the gateway routes, taken from the compiled DBC (its single source of truth)."""

    state: tuple[int, ...]  # AgentState of unit slot j (0 = head)
    aux: tuple[int, ...]  # AgentAux of unit slot j
    ahead_state: int  # the train ahead's tail AgentState, as received by this train
    ahead_aux: int
    behind_state: int  # the train behind's head AgentState, as received by this train
    behind_aux: int

    @classmethod
    def from_db(cls, db: TrainDb) -> "RadioIds":
        slots = range(db.max_units)
        return cls(tuple(db.agent_state(u).frame_id for u in slots), tuple(db.agent_aux(u).frame_id for u in slots),
                   db.radio_ahead_state.frame_id, db.radio_ahead_aux.frame_id, db.radio_behind_state.frame_id,
                   db.radio_behind_aux.frame_id)


@dataclass(frozen=True)
class Route:
    """Forward frame ``src_id`` heard on ``src_bus`` to ``dst_bus`` as ``dst_id`` over radio link ``link``."""

    src_bus: int
    src_id: int
    dst_bus: int
    dst_id: int
    link: str


def link_name(src_train: int, dst_train: int) -> str:
    """Name of the link carrying 0-based train ``src_train``'s frames to ``dst_train`` (1-based in the name)."""
    return f"{src_train + 1}>{dst_train + 1}"


def reverse_link_name(name: str) -> str:
    """``"a>b"`` -> ``"b>a"``: the other direction of the same radio pair."""
    a, sep, b = name.partition(">")
    if not sep or not a or not b or ">" in b:
        raise ValueError(f"radio link name {name!r} is not of the form 'a>b'")
    return f"{b}>{a}"


class _Hop:
    """One compiled route: where it goes, its link, and the slots holding both ends' positions."""

    __slots__ = ("dst_bus", "dst_id", "link", "name", "reverse")

    def __init__(self, route: Route, link: RadioLink) -> None:
        self.dst_bus = route.dst_bus
        self.dst_id = route.dst_id
        self.link = link
        self.name = route.link
        self.reverse = reverse_link_name(route.link)


class RadioGateway:
    """Routes frames between train buses over radio links, tracking each link end's position."""

    def __init__(
        self,
        routes: list[Route],
        links: dict[str, RadioLink],
        position_of: Callable[[int, bytes], float | None],
    ) -> None:
        self.links = links  # every link by name (stats live on the links)
        self._position_of = position_of
        self._table: dict[tuple[int, int], tuple[_Hop, ...]] = {}
        self._ids: dict[int, set[int]] = {}
        self._pos: dict[str, float] = {}  # link name -> last position of its sender end
        seen: set[Route] = set()
        for k, route in enumerate(routes):
            if route.link not in links:
                raise ValueError(f"route {k} ({route}) uses radio link {route.link!r}, not one of {sorted(links)}")
            if route in seen:
                raise ValueError(f"route {k} ({route}) is listed twice")
            seen.add(route)
            key = (route.src_bus, route.src_id)
            self._table[key] = self._table.get(key, ()) + (_Hop(route, links[route.link]),)
            self._ids.setdefault(route.src_bus, set()).add(route.src_id)

    def ids_for_bus(self, bus: int) -> set[int]:
        """The frame IDs the gateway listens to on ``bus`` (its acceptance filter)."""
        return set(self._ids.get(bus, ()))

    def position(self, link: str) -> float | None:
        """Last known position of the sender end of ``link`` (None before any frame carried one)."""
        return self._pos.get(link)

    def on_frame(self, bus: int, frame_id: int, data: bytes, t_ns: int) -> list[tuple[int, int, bytes, int]]:
        """Offer a frame heard on ``bus`` at ``t_ns`` to every matching route: (dst_bus, dst_id, data, deliver_t_ns) per delivery."""
        hops = self._table.get((bus, frame_id))
        if hops is None:
            return []
        pos = self._position_of(frame_id, data)
        out: list[tuple[int, int, bytes, int]] = []
        known = self._pos
        for hop in hops:
            if pos is not None:
                known[hop.name] = pos
            deliver = hop.link.offer(t_ns, known.get(hop.name), known.get(hop.reverse))
            if deliver is not None:
                out.append((hop.dst_bus, hop.dst_id, data, deliver))
        return out


def standard_routes(n_trains: int, units_per_train: int, forward_aux: bool, ids: RadioIds) -> list[Route]:
    """The rig's routing table: tail <-> head of each adjacent pair, AgentState (and AgentAux) both ways."""
    if n_trains < 1:
        raise ValueError(f"n_trains must be >= 1, got {n_trains}")
    if not 1 <= units_per_train <= len(ids.state):
        raise ValueError(f"units_per_train must be in 1..{len(ids.state)} (the DBC's unit slots), got {units_per_train}")
    tail = units_per_train - 1
    routes: list[Route] = []
    for i in range(n_trains - 1):
        ahead, behind = link_name(i, i + 1), link_name(i + 1, i)
        routes.append(Route(i, ids.state[tail], i + 1, ids.ahead_state, ahead))
        if forward_aux:
            routes.append(Route(i, ids.aux[tail], i + 1, ids.ahead_aux, ahead))
        routes.append(Route(i + 1, ids.state[0], i, ids.behind_state, behind))
        if forward_aux:
            routes.append(Route(i + 1, ids.aux[0], i, ids.behind_aux, behind))
    return routes


def link_rng(rng: np.random.Generator, src_train: int, dst_train: int) -> np.random.Generator:
    """A child Generator for link src_train -> dst_train (0-based), keyed by the pair, not by creation order.

    The child's seed is rng's SeedSequence with spawn key extended by (tag, src, dst), so a link's
    draws depend only on the run seed and its own name: adding trains or building links in another
    order (or in another process) leaves every other link's draws unchanged.
    """
    seq = rng.bit_generator.seed_seq
    if not isinstance(seq, np.random.SeedSequence):
        raise TypeError("radio links need a Generator seeded through a SeedSequence, e.g. np.random.default_rng(seed)")
    child = np.random.SeedSequence(
        entropy=seq.entropy,
        spawn_key=(*seq.spawn_key, _RADIO_SEED_TAG, src_train, dst_train),
        pool_size=seq.pool_size,
    )
    return np.random.Generator(type(rng.bit_generator)(child))


def build_links(cfg: RadioConfig, n_trains: int, rng: np.random.Generator) -> dict[str, RadioLink]:
    """Both directions of the radio link of every adjacent train pair, each with its own child Generator."""
    if n_trains < 1:
        raise ValueError(f"n_trains must be >= 1, got {n_trains}")
    links: dict[str, RadioLink] = {}
    for i in range(n_trains - 1):
        for src, dst in ((i, i + 1), (i + 1, i)):
            name = link_name(src, dst)
            links[name] = RadioLink(cfg, link_rng(rng, src, dst), name)
    return links


def build_gateway(sc, db, radio_rng) -> RadioGateway:
    """The radio gateway of a scenario's trains (links, routing table, position decoder) in Python: the real-time
    radio node's (``sc``: the Scenario, ``db``: its TrainDb)."""
    layout = TrainLayout.from_config(sc.trains)
    links = build_links(sc.radio, layout.n_trains, radio_rng)
    routes = standard_routes(layout.n_trains, layout.units_per_train, sc.radio.forward_aux, RadioIds.from_db(db))
    position_ids = {db.agent_state(k).frame_id for k in range(layout.units_per_train)}

    def position_of(frame_id: int, data: bytes) -> float | None:
        if frame_id not in position_ids or len(data) != db.by_id[frame_id].dlc:
            return None  # not a position frame, or a malformed one (receivers count it)
        return db.by_id[frame_id].decode(data)[0]

    return RadioGateway(routes, links, position_of)
