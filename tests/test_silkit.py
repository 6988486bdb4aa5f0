"""trainhil as Vector SIL Kit's CAN network simulator (hil/silkit): SIL Kit 5.0.3's own library and registry
(from the silkit-py wheel, `hil silkit install`), participants on a registry of the test's own on loopback, in
virtual time. Skipped where SIL Kit is not installed, except on CI (CI=true), which installs it and must run them."""
from __future__ import annotations

import json
import os

import pytest

from hil.can.frame import frame_bits, frame_duration_ns
from hil.silkit import capi
from hil.silkit.network_simulator import CanNetworkSimulator
from hil.silkit.runtime import SilKitUnavailable, find_runtime

STEP_NS = 1_000_000


@pytest.fixture(scope="module")
def runtime():
    try:
        return find_runtime()
    except SilKitUnavailable as exc:
        if os.environ.get("CI"):
            pytest.fail(f"CI must run the SIL Kit tests: {exc}")
        pytest.skip(str(exc))


def simulate(runtime, sends: dict[str, list[tuple]], depth: int = 64, until_ns: int = 5_000_000, fd: bool = False,
             flags_seen: list | None = None):
    """Run the rig (network simulator of bus1 at 500 kbit/s) and one participant per key of ``sends``, each sending
    its (step time, id, data[, flags]) frames, on a CAN FD bus (2 Mbit/s data phase) with ``fd``; returns (what the
    rig's controller received, the acknowledgements by sender, the simulator, and per participant (its last step
    before the frame came, frame end, id)); the received frames' flags go to ``flags_seen``."""
    from hil.silkit.session import LocalSimulation

    with LocalSimulation(["rig", *sends], runtime) as sim:
        rig = sim.participants["rig"]
        network = CanNetworkSimulator(sim.lib, rig.handle, "bus1", grid_ns=STEP_NS, tx_queue_depth=depth, fd=fd,
                                      data_bitrate=2_000_000 if fd else None)
        received: list[tuple[int, int, bytes]] = []
        acks: dict[str, list[tuple[int, int, int]]] = {name: [] for name in sends}
        seen: dict[str, list[tuple[int, int, int]]] = {name: [] for name in sends}
        last_step = {name: -1 for name in sends}
        controllers = {"rig": rig.can_controller("CAN1", "bus1")}
        controllers["rig"].on_frame(lambda t, i, d, f: (received.append((t, i, d)),
                                                       flags_seen.append(f) if flags_seen is not None else None))

        def rig_step(now: int, duration: int) -> None:
            network.step(now, duration)
            if now >= until_ns:
                rig.stop("done")

        rig.on_step(rig_step, network.step_ns)
        for name, frames in sends.items():
            controller = controllers[name] = sim.participants[name].can_controller("CAN1", "bus1")
            controller.on_transmit(lambda t, i, s, name=name: acks[name].append((t, i, s)))
            controller.on_frame(lambda t, i, d, f, name=name: seen[name].append((last_step[name], t, i)))

            def step(now: int, duration: int, controller=controller, frames=frames, name=name) -> None:
                last_step[name] = now
                for at, can_id, data, *flags in frames:
                    if at == now:
                        controller.send(can_id, data, *flags)

            sim.participants[name].on_step(step, STEP_NS)
        for controller in controllers.values():
            controller.set_baud_rate(500_000)
            controller.start()
        network.start()
        states = sim.run()
        assert set(states.values()) == {capi.STATE_SHUTDOWN}, states
    return received, acks, network, seen


def duration_ns(can_id: int, data: bytes) -> int:
    return frame_duration_ns(frame_bits(can_id, data), 500_000)


def test_the_lower_id_wins_and_the_other_ends_one_frame_later(runtime):
    data = bytes(range(8))
    received, acks, _, seen = simulate(runtime, {"ecuA": [(STEP_NS, 0x200, data)], "ecuB": [(STEP_NS, 0x100, data)],
                                                  "ecuC": []})
    first_end = STEP_NS + duration_ns(0x100, data)
    second_end = first_end + duration_ns(0x200, data)  # the engine's frame time includes the intermission
    assert received == [(first_end, 0x100, data), (second_end, 0x200, data)]
    assert acks == {"ecuB": [(first_end, 0x100, capi.TRANSMITTED)], "ecuA": [(second_end, 0x200, capi.TRANSMITTED)],
                    "ecuC": []}
    # both ended within (1 ms, 2 ms): a receiver has them before its step at 2 ms, after its step at 1 ms
    assert seen["ecuC"] == [(STEP_NS, first_end, 0x100), (STEP_NS, second_end, 0x200)]
    assert seen["ecuA"] == [(STEP_NS, first_end, 0x100)] and seen["ecuB"] == [(STEP_NS, second_end, 0x200)]


def test_can_fd_frames_on_a_can_fd_bus_and_a_format_the_bus_does_not_carry_is_refused(runtime):
    """On a CAN FD bus a 20-byte FDF frame is carried as CAN FD (timed with its 2 Mbit/s data phase, delivered
    flagged FDF and BRS); a classical frame there, and an FD frame on a classical bus, are acknowledged Canceled."""
    import trainhil_engine as engine

    payload = bytes(range(20))
    fd_flags = capi.FLAG_FDF | capi.FLAG_BRS
    flags: list[int] = []
    received, acks, network, _ = simulate(runtime, {"ecuA": [(STEP_NS, 0x120, payload, fd_flags),
                                                             (2 * STEP_NS, 0x121, bytes(8))]}, fd=True,
                                          flags_seen=flags)
    end = STEP_NS + engine.frame_duration_ns(0x120, payload, 500_000, 2_000_000, fd=True, brs=True)
    assert received == [(end, 0x120, payload)] and flags == [fd_flags]
    assert acks["ecuA"] == [(end, 0x120, capi.TRANSMITTED), (2 * STEP_NS, 0x121, capi.CANCELED)]
    assert network.format_refused == 1
    received, acks, network, _ = simulate(runtime, {"ecuA": [(STEP_NS, 0x120, payload, fd_flags)]})
    assert received == [] and acks["ecuA"] == [(STEP_NS, 0x120, capi.CANCELED)] and network.format_refused == 1


def test_a_full_tx_queue_reaches_the_sender(runtime):
    frames = [(STEP_NS, 0x300 + k, bytes([k])) for k in range(5)]
    received, acks, network, _ = simulate(runtime, {"ecuA": frames}, depth=2)
    statuses = [s for _, _, s in acks["ecuA"]]
    assert statuses.count(capi.TRANSMIT_QUEUE_FULL) == 3 and statuses.count(capi.TRANSMITTED) == 2
    assert [i for _, i, _ in received] == [0x300, 0x301] and network.queue_full == 3


def test_the_same_participants_give_the_same_run_twice(runtime):
    sends = {f"ecu{k}": [(t * STEP_NS, 0x100 + 16 * k + t, bytes([k, t])) for t in range(1, 4)] for k in range(3)}
    first = simulate(runtime, sends)[0]
    assert first == simulate(runtime, sends)[0]
    ends = [t for t, _, _ in first]
    assert len(first) == 9 and ends == sorted(ends)


# --------------------------------------------------------------------------- hil run --silkit


def test_a_silkit_run_without_external_units_is_the_virtual_run(runtime, tmp_path):
    """The rig in lockstep with SIL Kit, no participant but itself: the same frames and signals as without SIL Kit."""
    from hil.scenario import load_scenario
    from hil.session import run_scenario

    sc = load_scenario("seed000")
    plain = run_scenario(sc, tmp_path / "plain", duration_s=2, record=False).metrics
    silkit = run_scenario(sc, tmp_path / "silkit", duration_s=2, record=False, silkit="").metrics
    assert silkit["runtime"] == "silkit" and silkit["sim_time_s"] == pytest.approx(2.0)
    for key in ("frames_sent", "speed_error_max_abs_mps", "coupler_max_abs_m", "control_effort", "frame_latency_p99_s",
                "gap_min_overall_m", "jerk_rms_mps3"):
        assert silkit[key] == plain[key], key


def run_with_external_unit(runtime, out, duration_s: float = 3.0, faults: list | None = None,
                           error_states: list | None = None, wire: list | None = None):
    """seed000 --silkit with train1/unit2 as a SIL Kit participant of the test's (the firmware of ecu_sim on SIL
    Kit's CAN API, nothing of the rig's network), with the scenario's ``faults`` and the error states its controller
    is told appended to ``error_states`` and every frame of bus1 as it saw it, (end ns, id, data), its own at their
    acknowledgement, to ``wire``: (metrics, the unit's ECU, its transmit statuses)."""
    import threading

    from hil.runtime.assembly import assemble
    from hil.runtime.firmware import build_ecu
    from hil.runtime.train_db import load_train_db
    from hil.scenario import load_scenario
    from hil.session import run_scenario
    from hil.silkit.capi import Library
    from hil.silkit.participant import Participant
    from hil.silkit.registry import Registry

    sc = load_scenario("seed000", {"ecu.external": ["train1/unit2"], "ecu.join_timeout_s": 20.0,
                                   **({"faults": faults} if faults else {})})
    parts, db = assemble(sc), load_train_db(sc)
    ecu = build_ecu(parts, db, 1)
    inbox: list[tuple[int, bytes, float]] = []
    sent: list[int] = []
    with Registry(runtime) as registry:
        lib = Library(str(runtime.library))
        unit = Participant(lib, "train1/unit2", registry.uri)
        can = unit.can_controller("CAN1", "bus1")
        pending: dict[int, list[bytes]] = {}  # its own frames, by id, awaiting their acknowledgement

        def on_frame(t: int, i: int, d: bytes, f: int) -> None:
            if wire is not None:
                wire.append((t, i, d))
            if i in ecu.rx_ids:
                inbox.append((i, d, t * 1e-9))

        def on_transmit(t: int, i: int, status: int) -> None:
            sent.append(status)
            data = pending[i].pop(0)
            if wire is not None and status == capi.TRANSMITTED:
                wire.append((t, i, data))

        can.on_frame(on_frame)
        can.on_transmit(on_transmit)
        if error_states is not None:
            can.on_error_state(lambda t, state: error_states.append((t * 1e-9, state)))

        def step(now: int, duration: int) -> None:
            while inbox:
                ecu.on_frame(*inbox.pop(0))
            if now % 10_000_000 == 2_000_000:  # the ECU's 10 ms cycle, its phase on SIL Kit's 1 ms grid
                for frame_id, data in ecu.cycle(now * 1e-9):
                    pending.setdefault(frame_id, []).append(data)
                    can.send(frame_id, data)

        unit.on_step(step, STEP_NS)
        can.set_baud_rate(500_000)
        can.start()
        thread = threading.Thread(target=unit.run, daemon=True)
        thread.start()
        result = run_scenario(sc, out, duration_s=duration_s, record=False, silkit=registry.uri)
        thread.join(20)
        unit.close()
    return result.metrics, ecu, sent


def test_an_external_unit_joins_in_virtual_time_and_its_commands_are_applied(runtime, tmp_path):
    """The external unit's commands reach the plant (E2E and sequence accepted), every frame of its bus (its own
    included) is timed exactly without overlap, the run stays safe around it, and the same participants give the
    same run twice."""
    wire: list[tuple[int, int, bytes]] = []
    metrics, ecu, sent = run_with_external_unit(runtime, tmp_path / "a", wire=wire)
    assert metrics["sim_time_s"] == pytest.approx(3.0)
    # the CAN timing of bus1 as the external controller saw it: no two frames overlap, each takes its exact time
    wire.sort()
    gaps = [(b[0] - a[0]) - duration_ns(b[1], b[2]) for a, b in zip(wire, wire[1:])]
    assert len(wire) >= 5000 and min(gaps) >= 0  # back to back at best
    assert gaps.count(0) > 100  # and back to back often (a frame queued behind another starts at its end)
    assert ecu.counters.cycles == 300 and sent.count(capi.TRANSMITTED) == len(sent) >= 3 * 295
    assert not metrics["plant_command_rejects"], metrics["plant_command_rejects"]
    assert metrics["coupler_max_abs_m"] < 0.5 and not metrics["safety"]["collision"]["violated"]
    again, _, _ = run_with_external_unit(runtime, tmp_path / "b")
    for key in ("frames_sent", "speed_error_max_abs_mps", "coupler_max_abs_m", "control_effort", "jerk_rms_mps3"):
        assert again[key] == metrics[key], key


def test_an_external_controller_goes_bus_off_under_a_bus_fault_and_is_told(runtime, tmp_path):
    """Error frames on every TractionCmd_U02 (0x81) from 1 s: the engine's error confinement counts the SIL Kit
    controller's transmit errors like any node's; it is told error passive, then bus-off, then error active again
    after its recovery, as often as the engine counts them, and nothing once the fault is over."""
    states: list[tuple[float, int]] = []
    fault = {"kind": "bus_error_frames", "train": 1, "at_s": 1.0, "duration_s": 1.0, "probability": 1.0,
             "frame_ids": [0x81]}
    metrics, ecu, sent = run_with_external_unit(runtime, tmp_path, 3.0, [fault], states)
    kinds = [state for _, state in states]
    assert kinds[:3] == [capi.ERROR_PASSIVE, capi.BUS_OFF, capi.ERROR_ACTIVE], states
    assert 1.0 <= states[0][0] < states[1][0] < states[2][0] < 2.0
    node = metrics["faults"]["can_errors"]["buses"]["bus1"]["nodes"]["silkit:1"]  # the engine's count of it
    assert kinds.count(capi.BUS_OFF) == node["bus_off"] >= 1 and kinds.count(capi.ERROR_PASSIVE) == node["error_passive"]
    assert node["state"] == "error_active" and kinds[-1] == capi.ERROR_ACTIVE  # recovered once the fault ended
    assert all(t < 2.01 for t, _ in states)  # nothing after the fault's end (and its last recovery)
    assert metrics["safety"]["ecu_failure"]["violated"] is False  # a bus-off is the bus's fault, not the ECU's


def test_a_missing_external_participant_is_named_after_the_join_timeout(runtime, tmp_path, capsys):
    from hil.cli import main

    code = main(["run", "seed000", "--silkit", "--set", "ecu.external=['train1/unit2']", "--set",
                 "ecu.join_timeout_s=1.5", "--duration", "1", "--out", str(tmp_path / "o"), "--quiet"])
    captured = capsys.readouterr()
    assert code == 1
    assert "silkit registry=silkit://127.0.0.1:" in captured.out and "external=train1/unit2" in captured.out
    assert "SIL Kit participant(s) train1/unit2 did not join" in captured.err and "1.5 s" in captured.err
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert metrics["status"] == "failed" and "did not join" in metrics["error"]  # not "running": nothing to recover


def test_a_registry_uri_where_none_answers_is_named(runtime, tmp_path, capsys):
    import socket

    from hil.cli import main

    with socket.socket() as s:  # a free loopback port: nothing listens there once it is closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    code = main(["run", "seed000", "--silkit", f"silkit://127.0.0.1:{port}", "--duration", "1",
                 "--out", str(tmp_path / "o"), "--quiet"])
    assert code == 1
    assert f"no SIL Kit registry answers at silkit://127.0.0.1:{port}" in capsys.readouterr().err
    assert json.loads((tmp_path / "o" / "metrics.json").read_text())["status"] == "failed"


def build_c_ecu(runtime, into):
    """examples/silkit_ecu built with gcc into the folder ``into``, as its header comment says (warnings are errors)."""
    import subprocess
    from pathlib import Path

    source = Path(__file__).resolve().parents[1] / "examples" / "silkit_ecu" / "silkit_ecu.c"
    out = Path(into) / "silkit_ecu"
    home = str(runtime.home)
    subprocess.run(["gcc", "-O2", "-Wall", "-Werror", "-o", str(out), str(source), f"-L{home}", "-lSilKit",
                    f"-Wl,-rpath,{home}", "-lm"], check=True)
    return out


@pytest.fixture(scope="module")
def c_ecu(runtime, tmp_path_factory):
    """examples/silkit_ecu, built (skipped without gcc)."""
    import shutil

    if shutil.which("gcc") is None:
        pytest.skip("no gcc to build examples/silkit_ecu")
    return build_c_ecu(runtime, tmp_path_factory.mktemp("c-ecu"))


def run_with_c_ecu(runtime, binary, out, duration_s: float = 3.0):
    """seed000 --silkit for ``duration_s`` with the C ECU ``binary`` as train1/unit2: (metrics, what it printed)."""
    import subprocess

    from hil.scenario import load_scenario
    from hil.session import run_scenario
    from hil.silkit.registry import Registry

    sc = load_scenario("seed000", {"ecu.external": ["train1/unit2"], "ecu.join_timeout_s": 20.0})
    with Registry(runtime) as registry:
        ecu = subprocess.Popen([str(binary), "--registry", registry.uri, "--train", "1", "--unit", "2"],
                               stdout=subprocess.PIPE, text=True)
        try:
            metrics = run_scenario(sc, out, duration_s=duration_s, record=False, silkit=registry.uri).metrics
            printed, _ = ecu.communicate(timeout=20)
        finally:
            ecu.kill()
    return metrics, printed


def test_the_c_reference_ecu_drives_its_unit_in_virtual_time_deterministically(runtime, c_ecu, tmp_path):
    """examples/silkit_ecu (C, SIL Kit's C API, nothing of trainhil) as train1/unit2: its 300 cycles' frames pass
    the plant's and its neighbours' E2E checks, the couplers stay bounded, and the same run comes twice."""
    metrics, printed = run_with_c_ecu(runtime, c_ecu, tmp_path / "a")
    assert "sent 900 frames, dropped 0 with a bad E2E CRC, final state 110" in printed, printed
    assert not metrics["plant_command_rejects"]
    neighbour = metrics["e2e"]["train1/unit1/ecu"]  # receives unit 2's AgentState and AgentAux
    assert set(neighbour) <= {"OK", "INITIAL"} and neighbour["OK"] > 1000
    assert metrics["coupler_max_abs_m"] < 0.5 and not metrics["safety"]["collision"]["violated"]
    again, _ = run_with_c_ecu(runtime, c_ecu, tmp_path / "b")
    for key in ("frames_sent", "speed_error_max_abs_mps", "coupler_max_abs_m", "control_effort"):
        assert again[key] == metrics[key], key


def test_a_participant_killed_mid_run_is_recorded_and_the_fail_safe_holds_its_unit(runtime, c_ecu, tmp_path):
    """The C ECU as train1/unit2 dies abruptly at 2 s (``--crash-at``, SIL Kit never told): the rig records it as
    that ECU's failure at the time it was lost, leaves SIL Kit (whose coordinated time cannot advance past a lost
    participant) and runs on to its end in virtual time; the plant's fail-safe brakes the silent unit, and the
    files are complete and readable."""
    import subprocess

    from hil.record.integrity import check_run_dir
    from hil.scenario import load_scenario
    from hil.session import run_scenario
    from hil.silkit.registry import Registry

    sc = load_scenario("seed000", {"ecu.external": ["train1/unit2"], "ecu.join_timeout_s": 20.0})
    with Registry(runtime) as registry:
        ecu = subprocess.Popen([str(c_ecu), "--registry", registry.uri, "--crash-at", "2"], stdout=subprocess.PIPE,
                               text=True)
        try:
            result = run_scenario(sc, tmp_path, duration_s=6, silkit=registry.uri)
            printed, _ = ecu.communicate(timeout=20)
        finally:
            ecu.kill()
    assert "crashing at t = 2.000 s" in printed and ecu.returncode == 3, printed
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["interrupted"] is False and metrics["sim_time_s"] == pytest.approx(6.0)
    lost = metrics["safety"]["ecu_failure"]["violations"][0]
    assert lost["where"] == "train1/unit2" and "disconnected without shutting down" in lost["text"]
    assert 2.0 <= lost["t_s"] <= 2.01  # lost in the step it died in
    braked = [e for e in result.log.events if e.source == "plant" and e.t > lost["t_s"] and "unit 2" in e.text
              and "train 1" in e.text]
    assert braked, "the plant's fail-safe did not act on the lost unit"
    assert metrics["coupler_max_abs_m"] < 5.0 and not metrics["safety"]["collision"]["violated"]
    assert metrics["silkit"]["controllers"]["bus1"] == 1  # it took part, though gone by the end
    report = check_run_dir(tmp_path, expect_complete=True)
    assert report.ok, report.problems


@pytest.fixture
def two_hosts():
    """Two network namespaces joined by a veth pair, ``(host A, host B, A's address)``, made here and removed after;
    skipped with the reason where they cannot be made (no iproute2, no privilege to make namespaces)."""
    import shutil
    import subprocess

    if shutil.which("ip") is None or shutil.which("ss") is None:
        pytest.skip("no iproute2 (ip, ss) to make and watch network namespaces")
    tag = os.getpid() % 100000
    a, b, subnet = f"tha{tag}", f"thb{tag}", f"10.213.{tag % 250}"

    def ip(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["ip", *args], capture_output=True, text=True)

    steps = [("netns", "add", a), ("netns", "add", b),
             ("link", "add", f"va{tag}", "type", "veth", "peer", "name", f"vb{tag}"),
             ("link", "set", f"va{tag}", "netns", a), ("link", "set", f"vb{tag}", "netns", b),
             ("-n", a, "addr", "add", f"{subnet}.1/30", "dev", f"va{tag}"),
             ("-n", b, "addr", "add", f"{subnet}.2/30", "dev", f"vb{tag}"),
             ("-n", a, "link", "set", f"va{tag}", "up"), ("-n", b, "link", "set", f"vb{tag}", "up"),
             ("-n", a, "link", "set", "lo", "up"), ("-n", b, "link", "set", "lo", "up")]
    try:
        for step in steps:
            done = ip(*step)
            if done.returncode:
                pytest.skip(f"cannot make two network hosts here (ip {' '.join(step)}: {done.stderr.strip()})")
        yield a, b, f"{subnet}.1"
    finally:
        ip("netns", "del", a)
        ip("netns", "del", b)


def _peer_connections(namespace: str, host: str, registry_port: str, seen: list, stop) -> None:
    """Watch ``namespace``'s established TCP connections for one to ``host`` that is not the registry's (a
    participant-to-participant link over the veth) until ``stop`` is set."""
    import subprocess

    while not stop.is_set():
        out = subprocess.run(["ip", "netns", "exec", namespace, "ss", "-tnH", "state", "established"],
                             capture_output=True, text=True).stdout
        seen += [line for line in out.splitlines()
                 if (peer := line.split()[-1]).startswith(f"{host}:") and not peer.endswith(f":{registry_port}")]
        stop.wait(0.1)


def test_the_rig_and_the_c_ecu_on_two_hosts(runtime, c_ecu, two_hosts, tmp_path):
    """The registry and the rig on host A, the C ECU on host B (two network namespaces joined by veth): the ECU
    joins over TCP (the rig's domain sockets off, through its --silkit-config), drives train1/unit2 in virtual time,
    and a participant-to-participant TCP connection between the hosts is seen."""
    import subprocess
    import sys
    import threading

    from hil.silkit.registry import Registry

    host_a, host_b, address = two_hosts
    on = {"a": ["ip", "netns", "exec", host_a], "b": ["ip", "netns", "exec", host_b]}
    config = tmp_path / "rig.yaml"
    config.write_text("Middleware:\n  EnableDomainSockets: false\n")
    with Registry(runtime, host=address, launcher=on["a"]) as registry:
        seen: list[str] = []
        stop = threading.Event()
        watcher = threading.Thread(target=_peer_connections,
                                   args=(host_b, address, registry.uri.rsplit(":", 1)[1], seen, stop))
        ecu = subprocess.Popen([*on["b"], str(c_ecu), "--registry", registry.uri], stdout=subprocess.PIPE, text=True)
        watcher.start()
        try:
            rig = subprocess.run([*on["a"], sys.executable, "-c", "import sys; from hil.cli import main; sys.exit(main())",
                                  "run", "seed000", "--silkit", registry.uri, "--silkit-config", str(config),
                                  "--external", "train1/unit2", "--duration", "3", "--out", str(tmp_path / "o"),
                                  "--no-record", "--quiet"], capture_output=True, text=True, timeout=120)
            printed, _ = ecu.communicate(timeout=30)
        finally:
            stop.set()
            watcher.join()
            ecu.kill()
    assert rig.returncode == 0, rig.stderr
    assert "sent 900 frames, dropped 0 with a bad E2E CRC, final state 110" in printed, printed
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert metrics["silkit"]["controllers"]["bus1"] == 1 and not metrics["plant_command_rejects"]
    assert metrics["e2e"]["train1/unit1/ecu"]["OK"] > 1000  # unit 2's frames reached its neighbour on host A
    assert seen, "no TCP connection between the participants on the two hosts was seen"


def test_vector_s_system_controller_starts_the_rig_and_the_c_ecu(runtime, c_ecu, tmp_path):
    """Vector's sil-kit-system-controller (unchanged, from the runtime) coordinates: the rig leaves that role to it
    (--silkit-no-system-controller); the C ECU drives its unit and the controller sees the simulation end."""
    import subprocess

    from hil.cli import main
    from hil.silkit.registry import Registry

    with Registry(runtime) as registry:
        controller = subprocess.Popen([str(runtime.tool("sil-kit-system-controller")), "--connect-uri", registry.uri,
                                       "--log", "info", "trainhil", "train1/unit2"],
                                      stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                      text=True)
        ecu = subprocess.Popen([str(c_ecu), "--registry", registry.uri], stdout=subprocess.PIPE, text=True)
        try:
            code = main(["run", "seed000", "--silkit", registry.uri, "--silkit-no-system-controller", "--external",
                         "train1/unit2", "--silkit-network", "bus2=CAN2", "--duration", "2", "--out",
                         str(tmp_path / "o"), "--no-record", "--quiet"])
            printed, _ = ecu.communicate(timeout=20)
            said, _ = controller.communicate(timeout=20)
        finally:
            ecu.kill()
            controller.kill()
    assert code == 0
    assert "sent 600 frames, dropped 0" in printed, printed
    assert "Simulation is now running" in said and "Simulation ended" in said and controller.returncode == 0, said
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert metrics["silkit"]["system_controller"] is False and not metrics["plant_command_rejects"]
    assert metrics["silkit"]["networks"] == ["bus1", "CAN2", "bus3"]  # --silkit-network renames one


def test_realtime_silkit_couples_sil_kit_time_to_the_wall_clock(runtime, tmp_path):
    """--realtime --silkit --pace 4: SIL Kit's AnimationFactor 0.25 on the rig's participant, so 2 simulated
    seconds take at least 0.5 s of wall time, every one of the 4,000 half steps (0.5 ms) timed against the wall
    clock in metrics.json; the run is the virtual one (the same frames as without pacing)."""
    import time

    from hil.cli import main

    wall0 = time.perf_counter()
    code = main(["run", "seed000", "--realtime", "--pace", "4", "--silkit", "--duration", "2", "--out",
                 str(tmp_path / "paced"), "--no-record", "--quiet"])
    wall = time.perf_counter() - wall0
    assert code == 0
    paced = json.loads((tmp_path / "paced" / "metrics.json").read_text())
    assert paced["runtime"] == "silkit" and paced["pace"] == 4.0 and wall >= 0.5
    lateness = paced["silkit"]["step_lateness_ms"]
    assert lateness["steps"] == 4000 and 0 <= lateness["p50"] <= lateness["max"]
    assert main(["run", "seed000", "--silkit", "--duration", "2", "--out", str(tmp_path / "free"), "--no-record",
                 "--quiet"]) == 0
    free = json.loads((tmp_path / "free" / "metrics.json").read_text())
    assert "step_lateness_ms" not in free["silkit"]
    for key in ("frames_sent", "speed_error_max_abs_mps", "coupler_max_abs_m"):
        assert paced[key] == free[key], key


@pytest.mark.parametrize("argv, message", [
    (["--silkit-step", "0.002"], "--silkit-step only with --silkit"),
    (["--silkit", "--silkit-step", "0.0000000015"], "whole, even number of ns"),
    (["--silkit", "--silkit-step", "0.0010000005"], "whole, even number of ns"),
    (["--silkit", "--ideal"], "not with --ideal"),
    (["--silkit", "--realtime", "--ecus-per-process", "2"], "--ecus-per-process, --run, --scheduling, --idle-latency-us, --cpu-layout and --turns are for the process rig"),
    (["--silkit", "--realtime", "--scheduling", "fifo"], "--ecus-per-process, --run, --scheduling, --idle-latency-us, --cpu-layout and --turns are for the process rig"),
    (["--silkit", "--realtime", "--cpu-layout", "none"], "--cpu-layout and --turns are for the process rig"),
    (["--silkit", "--realtime", "--turns", "off"], "--cpu-layout and --turns are for the process rig"),
    (["--silkit", "--silkit-config", "/nonexistent/sk.yaml"], "--silkit-config /nonexistent/sk.yaml: cannot read"),
    (["--silkit", "--silkit-network", "bus9=CAN9"], "--silkit-network bus9: no such bus"),
    (["--silkit", "--silkit-network", "bus1"], "expected BUS=NETWORK"),
    (["--silkit", "--silkit-network", "bus1=CAN1", "--silkit-network", "bus2=CAN1"], "two buses on one"),
])
def test_silkit_options_that_cannot_work_are_exit_2_before_anything_is_written(tmp_path, capsys, argv, message):
    from hil.cli import main

    assert main(["run", "seed000", *argv, "--duration", "1", "--out", str(tmp_path / "o")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_a_lost_participant_that_is_no_unit_of_the_rig_does_not_hang_it(runtime, c_ecu, tmp_path):
    """Vector's system controller requires the rig and a C participant the rig knows nothing of (not in
    ecu.external); that participant crashes at 1 s. SIL Kit's time stops (system state Error): the rig notices,
    records it, leaves SIL Kit and finishes its run in virtual time."""
    import subprocess

    from hil.cli import main
    from hil.silkit.registry import Registry

    with Registry(runtime) as registry:
        controller = subprocess.Popen([str(runtime.tool("sil-kit-system-controller")), "--connect-uri", registry.uri,
                                       "--log", "off", "trainhil", "train1/unit2"], stdin=subprocess.DEVNULL,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        other = subprocess.Popen([str(c_ecu), "--registry", registry.uri, "--crash-at", "1"], stdout=subprocess.DEVNULL)
        try:
            code = main(["run", "seed000", "--silkit", registry.uri, "--silkit-no-system-controller", "--duration", "3",
                         "--out", str(tmp_path / "o"), "--no-record", "--quiet"])
            other.wait(20)
        finally:
            other.kill()
            controller.kill()
    assert code == 0
    metrics = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert metrics["sim_time_s"] == pytest.approx(3.0) and metrics["interrupted"] is False
    assert [lost["participant"] for lost in metrics["silkit"]["lost"]] == ["train1/unit2"]
    assert 1.0 <= metrics["silkit"]["lost"][0]["t_s"] <= 1.01
    assert metrics["safety"]["ecu_failure"]["violated"] is False  # none of the rig's units was lost


@pytest.mark.parametrize("config", ["Experimental:\n  TimeSynchronization:\n    AnimationFactor: 2.0\n",
                                    '{"Logging": {"Sinks": [{"Type": "Stdout"}]}}'])
def test_a_silkit_config_pacing_cannot_join_is_refused_with_realtime(tmp_path, capsys, config):
    """--realtime adds an Experimental block to the rig's configuration: a file with its own, or a JSON one (which
    cannot take a second block), is exit 2 before anything is written."""
    from hil.cli import main

    path = tmp_path / "rig.yaml"
    path.write_text(config)
    assert main(["run", "seed000", "--realtime", "--silkit", "--silkit-config", str(path), "--duration", "1",
                 "--out", str(tmp_path / "o")]) == 2
    assert "adds an Experimental block" in capsys.readouterr().err and not (tmp_path / "o").exists()
