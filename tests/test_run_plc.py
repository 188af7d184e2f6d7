#!/usr/bin/python3
"""Integration test of `cellsight run --sim` with real Modbus clients playing the PLC (pymodbus 3.0, Debian).

Starts `cellsight run --sim --parts N --wait-plc --truth-log FILE --port P`, then, all at the same time:
  PLC A   the handshake of DESIGN.md, written for register map version 2 (checks MAP_VERSION = 2): TRIGGER_ENABLE,
          waits for RESULT_VALID, reads the 35-register result block (200-234, pose uncertainties included) in one
          FC03, checks that both sequence copies equal RESULT_SEQ and that the sequence is new, sets RESULT_ACK,
          waits for RESULT_VALID to drop, clears RESULT_ACK. Once it drops its connection in the middle of a result
          (read, not yet acknowledged) and reconnects: the same result must still be there, unchanged, and is taken
          once.
  PLC B   a second client polling the result block with FC04 (input registers) without acknowledging; A does not
          acknowledge a result before B has seen it, so B must see exactly the same results.
  abuser  malformed frames, illegal functions and addresses, writes into read-only blocks: each must get its
          exception reply (or, for broken framing, a closed connection), while A and B keep being served.
Then checks: sequence numbers 1..N without gaps, each result taken exactly once by A and seen once by B with the
same contents, acquisition ids and result codes plausible, the pose and sigma registers consistent (a result that is
not ok has every pose value 0x80000000 and every sigma 0xFFFF; an ok one has X, Y, RZ; an axis whose value is
0x80000000 has sigma 0xFFFF; Z, RX, RY and the sigmas may be invalid where the recogniser does not estimate them),
the decided part ids and poses against the simulator's truth (from --truth-log) within the given tolerances (a
catalogue part that was never taught must come out "unknown part"), and cellsight's clean exit (0) once the PLC has
all results.

Truth: with --sim-oracle the run decides from the simulator's truth (ids = catalogue index + 1): the check is then
exact and tests the runtime, not recognition. With --models DIR the production recogniser decides; the PLC id of
each part name comes from DIR/manifest.yaml, and the expected pose is DESIGN.md's pose, the displacement from the
taught template about its centroid: cellsight writes the truth of each template ("sim seed N" scans), its centroid
and the simulator's nominal centre into the truth log, and expected_pose() composes them exactly. Templates not
taught on the simulated cell: poses from --template-poses FILE (JSON {"part": {"x_m", "y_m", "theta_deg"}}), else
the manifest's template_pose / truth_pose keys, else pose 0.

usage: test_run_plc.py --cellsight BIN --calibration FILE (--models DIR | --sim-oracle) [--config FILE]
                       [--parts N] [--seed S] [--sim-parts A,B] [--min-correct F] [--pose-tol-mm D]
                       [--theta-tol-deg D]
exit: 0 pass, 1 fail (a JSON summary and one line per problem on stdout), 2 cannot run (pymodbus, binary, ...).
"""

import argparse
import json
import math
import os
import random
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time

try:
    from pymodbus.client import ModbusTcpClient
except ImportError as error:  # pragma: no cover - reported as "cannot run"
    print(f"test_run_plc: pymodbus 3 is needed (apt install python3-pymodbus python3-serial-asyncio): {error}")
    sys.exit(2)

# Register map (drivers/modbus/register_map.hpp, DESIGN.md): literal on purpose, this is the PLC's view.
CONTROL = 0
PLC_HEARTBEAT = 4
STATUS = 100
RESULT = 200
RESULT_COUNT = 35  # 200-234, map version 2: one read
MAP_VERSION_INDEX = 10  # register 110 in a status read from 100
MAP_VERSION = 2
TRIGGER_ENABLE = 1 << 0
RESULT_ACK = 1 << 2
READY = 1 << 0
RESULT_VALID = 1 << 4
ERROR = 1 << 6
INVALID_S32 = -0x80000000
INVALID_SIGMA = 0xFFFF
AXES = (("x_um", "sigma_x_um"), ("y_um", "sigma_y_um"), ("z_um", "sigma_z_um"), ("rx_mdeg", "sigma_rx_mdeg"),
        ("ry_mdeg", "sigma_ry_mdeg"), ("rz_mdeg", "sigma_rz_mdeg"))
CODE_OK = 0
CODE_UNKNOWN = 2
UNIT = 1


def u32(regs, i):
    return (regs[i] << 16) | regs[i + 1]


def s32(regs, i):
    v = u32(regs, i)
    return v - (1 << 32) if v & 0x80000000 else v


def decode(regs):
    """Result block 200-234 (map version 2), high word first (README "Register table"); markers kept as read."""
    return {
        "seq": u32(regs, 0), "acq_id": u32(regs, 2), "code": regs[4], "part_id": regs[5], "confidence": regs[6],
        "source": regs[7], "x_um": s32(regs, 8), "y_um": s32(regs, 10), "z_um": s32(regs, 12),
        "rx_mdeg": s32(regs, 14), "ry_mdeg": s32(regs, 16), "rz_mdeg": s32(regs, 18),
        "timestamp_us": (u32(regs, 20) << 32) | u32(regs, 22), "cycle_ms": regs[24], "seq_copy": u32(regs, 25),
        "sigma_x_um": regs[27], "sigma_y_um": regs[28], "sigma_z_um": regs[29], "sigma_rx_mdeg": regs[30],
        "sigma_ry_mdeg": regs[31], "sigma_rz_mdeg": regs[32], "seq_copy2": u32(regs, 33),
    }


def whole(block):
    """A PLC accepts the block only when both sequence copies equal RESULT_SEQ."""
    return block["seq"] == block["seq_copy"] == block["seq_copy2"]


def pose_format_problems(block):
    """What is wrong with the pose and sigma registers of one result, judged by the README's rules alone."""
    found = []
    if block["code"] != CODE_OK:
        if any(block[value] != INVALID_S32 for value, _ in AXES) or any(
                block[sigma] != INVALID_SIGMA for _, sigma in AXES):
            found.append(f"code {block['code']} carries a pose or a sigma")
        return found
    for value in ("x_um", "y_um", "rz_mdeg"):
        if block[value] == INVALID_S32:
            found.append(f"ok without {value}")
    for value, sigma in AXES:
        if block[value] == INVALID_S32 and block[sigma] != INVALID_SIGMA:
            found.append(f"{sigma} {block[sigma]} for an invalid {value}")
    return found


class Problems:
    def __init__(self):
        self.lock = threading.Lock()
        self.items = []

    def add(self, what):
        with self.lock:
            self.items.append(what)
        print(f"PROBLEM: {what}", flush=True)


def free_port():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def ok(response):
    return response is not None and not response.isError()


class Shared:
    """What the clients tell each other."""

    def __init__(self, parts):
        self.parts = parts
        self.cond = threading.Condition()
        self.seen_by_b = {}   # seq -> block
        self.taken_by_a = {}  # seq -> block
        self.stop = False


def plc_a(port, shared, problems, deadline, reconnect_at):
    """The handshake PLC; drops and re-opens its connection once, holding an unacknowledged result."""
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3, retries=0)
    if not client.connect():
        problems.add("PLC A cannot connect")
        return
    heartbeat = 0
    last_seq = 0
    reconnected = False
    re_presented = 0

    def write(address, value):
        nonlocal client
        if not ok(client.write_register(address, value, slave=UNIT)):
            raise RuntimeError(f"write {address}={value} failed")

    def status():
        nonlocal heartbeat
        heartbeat = (heartbeat + 1) & 0xFFFF
        write(PLC_HEARTBEAT, heartbeat)
        rr = client.read_holding_registers(STATUS, 11, slave=UNIT)
        if not ok(rr):
            raise RuntimeError(f"status read failed: {rr}")
        return rr.registers

    try:
        version = status()[MAP_VERSION_INDEX]
        if version != MAP_VERSION:
            raise RuntimeError(f"MAP_VERSION is {version}, PLC A is written for {MAP_VERSION}")
        write(CONTROL, TRIGGER_ENABLE)
        while len(shared.taken_by_a) < shared.parts and time.monotonic() < deadline and not shared.stop:
            st = status()
            if not st[0] & RESULT_VALID:
                time.sleep(0.002)
                continue
            rr = client.read_holding_registers(RESULT, RESULT_COUNT, slave=UNIT)
            if not ok(rr):
                raise RuntimeError(f"result read failed: {rr}")
            block = decode(rr.registers)
            if not whole(block):
                problems.add(f"PLC A: torn block {block['seq']} / {block['seq_copy']} / {block['seq_copy2']}")
                continue
            if block["seq"] == last_seq:
                re_presented += 1  # already taken (after the reconnect): a PLC checks the sequence is new
                write(CONTROL, TRIGGER_ENABLE | RESULT_ACK)
            else:
                if block["seq"] != last_seq + 1:
                    problems.add(f"PLC A: sequence jumped from {last_seq} to {block['seq']}")
                last_seq = block["seq"]
                if block["seq"] in shared.taken_by_a:
                    problems.add(f"PLC A: result {block['seq']} taken twice")
                shared.taken_by_a[block["seq"]] = block
                # B must see it before it goes away.
                with shared.cond:
                    if not shared.cond.wait_for(lambda: block["seq"] in shared.seen_by_b or shared.stop, timeout=10):
                        problems.add(f"PLC B did not see result {block['seq']} within 10 s")
                if not reconnected and len(shared.taken_by_a) == reconnect_at:
                    # Drop the connection holding the result, come back, find it again (same sequence number).
                    reconnected = True
                    client.close()
                    time.sleep(0.2)
                    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3, retries=0)
                    if not client.connect():
                        raise RuntimeError("reconnect failed")
                    rr = client.read_holding_registers(RESULT, RESULT_COUNT, slave=UNIT)
                    if not ok(rr):
                        raise RuntimeError("result read after reconnect failed")
                    again = decode(rr.registers)
                    st = status()
                    if not st[0] & RESULT_VALID or again != block:
                        problems.add(f"after reconnecting the unacknowledged result {block['seq']} was not there "
                                     f"unchanged (status {st[0]:#x}, block {again})")
                    write(CONTROL, TRIGGER_ENABLE)  # CONTROL survives the reconnect: write it again anyway
                write(CONTROL, TRIGGER_ENABLE | RESULT_ACK)
            while time.monotonic() < deadline:
                if not status()[0] & RESULT_VALID:
                    break
                time.sleep(0.002)
            write(CONTROL, TRIGGER_ENABLE)
    except Exception as error:  # noqa: BLE001 - any failure is a test problem
        problems.add(f"PLC A: {type(error).__name__}: {error}")
    finally:
        shared.a_re_presented = re_presented
        shared.a_reconnected = reconnected
        client.close()


def plc_b(port, shared, problems, deadline):
    """A second client: polls the result block with FC04 and records each new result."""
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3, retries=0)
    if not client.connect():
        problems.add("PLC B cannot connect")
        return
    last = 0
    try:
        while time.monotonic() < deadline and not shared.stop and len(shared.seen_by_b) < shared.parts:
            rr = client.read_input_registers(RESULT, RESULT_COUNT, slave=UNIT)
            if not ok(rr):
                raise RuntimeError(f"FC04 read failed: {rr}")
            block = decode(rr.registers)
            if block["seq"] == 0 or block["seq"] == last or not whole(block):
                time.sleep(0.001)
                continue
            last = block["seq"]
            with shared.cond:
                if block["seq"] in shared.seen_by_b:
                    problems.add(f"PLC B: result {block['seq']} came back")
                shared.seen_by_b[block["seq"]] = block
                shared.cond.notify_all()
    except Exception as error:  # noqa: BLE001
        problems.add(f"PLC B: {type(error).__name__}: {error}")
    finally:
        client.close()


def raw_request(port, frame, expect_close=False):
    """Sends one raw frame; returns the reply bytes, or None when the server closed the connection."""
    with socket.create_connection(("127.0.0.1", port), timeout=3) as s:
        s.sendall(frame)
        data = b""
        try:
            while len(data) < 9:
                chunk = s.recv(260)
                if not chunk:
                    return None if not data else data
                data += chunk
                if len(data) >= 6 and len(data) >= 6 + struct.unpack(">H", data[4:6])[0]:
                    break
        except socket.timeout:
            return "timeout"
        return data


def mbap(tid, pdu, protocol=0, unit=UNIT, length=None):
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1 if length is None else length, unit) + pdu


def abuser(port, shared, problems, rounds):
    """Illegal functions and addresses (exception replies) and broken framing (closed), over and over."""
    cases = [
        ("read coils (FC01)", struct.pack(">BHH", 0x01, 0, 1), 0x01),
        ("FC43 device id", struct.pack(">BBB", 0x2B, 0x0E, 0x01), 0x01),
        ("read holding 150 (gap)", struct.pack(">BHH", 0x03, 150, 1), 0x02),
        ("read input 0 (command block is holding only)", struct.pack(">BHH", 0x04, 0, 1), 0x02),
        ("read past the result block", struct.pack(">BHH", 0x03, 230, 10), 0x02),
        ("read one more than the result block", struct.pack(">BHH", 0x04, 200, 36), 0x02),
        ("write RESULT_SEQ (read-only)", struct.pack(">BHH", 0x06, 200, 1), 0x02),
        ("write STATUS with FC16 (read-only)", struct.pack(">BHHBH", 0x10, 100, 1, 2, 0xFFFF), 0x02),
        ("read 126 registers", struct.pack(">BHH", 0x03, 0, 126), 0x03),
        ("FC16 byte count does not match", struct.pack(">BHHBH", 0x10, 0, 2, 2, 0), 0x03),
    ]
    broken = [
        ("protocol id 0x1234", lambda tid: mbap(tid, struct.pack(">BHH", 0x03, 200, 1), protocol=0x1234)),
        ("length 300", lambda tid: mbap(tid, struct.pack(">BHH", 0x03, 200, 1), length=300)),
        ("length 1", lambda tid: struct.pack(">HHHB", tid, 0, 1, UNIT)),
    ]
    rng = random.Random(5)
    tid = 100
    answered = 0
    try:
        for _ in range(rounds):
            if shared.stop:
                break
            for name, pdu, code in cases:
                tid += 1
                reply = raw_request(port, mbap(tid, pdu))
                want = struct.pack(">HHHBBB", tid, 0, 3, UNIT, pdu[0] | 0x80, code)
                if reply != want:
                    problems.add(f"abuser: {name}: expected exception {code:#04x} {want.hex()}, got "
                                 f"{reply.hex() if isinstance(reply, bytes) else reply}")
                else:
                    answered += 1
            for name, make in broken:
                tid += 1
                reply = raw_request(port, make(tid))
                if reply is not None:  # framing that cannot be resynchronised: the server closes the connection
                    problems.add(f"abuser: {name}: expected the connection closed, got "
                                 f"{reply.hex() if isinstance(reply, bytes) else reply}")
            # Random bytes: anything but a hang or a crash is fine.
            tid += 1
            garbage = bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 300)))
            reply = raw_request(port, garbage)
            if reply == "timeout":
                # An incomplete frame is dropped after the byte timeout: the server closes, never hangs.
                problems.add("abuser: random bytes left the connection hanging")
            time.sleep(0.05)
    except Exception as error:  # noqa: BLE001
        problems.add(f"abuser: {type(error).__name__}: {error}")
    shared.abuse_answered = answered


def expected_pose(scan, template, reference):
    """DESIGN.md's pose of a scan relative to its template: p_scan = c + R(theta)(p_template - c) + (x, y).

    The simulator places a part at p = C0 + R(theta_p) p_part + t_p (C0 its nominal centre). With the template's
    truth (t_t, theta_t) and its centroid c (from the truth log's template lines): theta = theta_s - theta_t,
    t = t_s - t_t + (I - R(theta)) (C0 + t_t - c). Without template truth: the difference of the poses (reference
    given) or the scan's own pose (template taught at pose 0)."""
    if template and template.get("seed") is not None:
        theta_deg = scan["theta_deg"] - template["pose"]["theta_deg"]
        a = math.radians(theta_deg)
        ex = template["nominal_centre_m"][0] + template["pose"]["x_m"] - template["centroid_m"][0]
        ey = template["nominal_centre_m"][1] + template["pose"]["y_m"] - template["centroid_m"][1]
        rx = math.cos(a) * ex - math.sin(a) * ey
        ry = math.sin(a) * ex + math.cos(a) * ey
        return (scan["x_m"] - template["pose"]["x_m"] + ex - rx, scan["y_m"] - template["pose"]["y_m"] + ey - ry,
                theta_deg)
    ref = reference or {}
    return (scan["x_m"] - ref.get("x_m", 0.0), scan["y_m"] - ref.get("y_m", 0.0),
            scan["theta_deg"] - ref.get("theta_deg", 0.0))


def load_manifest_ids(models_dir):
    try:
        import yaml
    except ImportError:
        return None, "python3-yaml is needed to read manifest.yaml"
    path = os.path.join(models_dir, "manifest.yaml")
    try:
        with open(path, encoding="utf-8") as f:
            manifest = yaml.safe_load(f)
    except OSError as error:
        return None, f"{path}: {error}"
    parts = manifest.get("parts") if isinstance(manifest, dict) else None
    if isinstance(parts, dict):
        parts = [dict(v, name=k) for k, v in parts.items()]
    ids, poses = {}, {}
    for entry in parts or []:
        if not isinstance(entry, dict) or "name" not in entry:
            continue
        for key in ("plc_id", "id", "part_id"):
            if key in entry:
                ids[entry["name"]] = int(entry[key])
                break
        for key in ("template_pose", "truth_pose"):
            if isinstance(entry.get(key), dict):
                poses[entry["name"]] = entry[key]
    if not ids:
        return None, f"{path}: no parts with a PLC id (keys plc_id / id / part_id)"
    return (ids, poses), None


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cellsight", required=True, help="the cellsight executable")
    parser.add_argument("--config", help="configuration (cellsight --config)")
    parser.add_argument("--calibration", required=True)
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--models", help="trained model database: the production recogniser decides")
    group.add_argument("--sim-oracle", action="store_true", help="decisions from the simulator's truth (runtime only)")
    parser.add_argument("--parts", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--sim-parts", help="only these catalogue parts arrive (cellsight run --sim-parts)")
    parser.add_argument("--reconnect-at", type=int, default=3, help="PLC A reconnects holding this result")
    parser.add_argument("--min-correct", type=float, default=0.95,
                        help="share of parts that must come back ok with the true part id")
    parser.add_argument("--pose-tol-mm", type=float, default=5.0)
    parser.add_argument("--theta-tol-deg", type=float, default=1.0)
    parser.add_argument("--template-poses", help="JSON: {part: {x_m, y_m, theta_deg}} of the taught templates")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds for the whole run")
    parser.add_argument("--keep", help="keep the run's log and truth in this folder")
    args = parser.parse_args()

    if not os.access(args.cellsight, os.X_OK):
        print(f"test_run_plc: {args.cellsight} is not an executable")
        return 2
    expected_ids, template_poses = None, {}
    if args.models:
        loaded, why = load_manifest_ids(args.models)
        if loaded is None:
            print(f"test_run_plc: {why}")
            return 2
        expected_ids, template_poses = loaded
    if args.template_poses:
        with open(args.template_poses, encoding="utf-8") as f:
            template_poses = json.load(f)

    work = args.keep or tempfile.mkdtemp(prefix="cellsight_run_plc_")
    os.makedirs(work, exist_ok=True)
    truth_path = os.path.join(work, "truth.jsonl")
    log_path = os.path.join(work, "cellsight.log")
    port = free_port()
    command = [args.cellsight]
    if args.config:
        command += ["--config", args.config]
    command += ["run", "--sim", "--parts", str(args.parts), "--seed", str(args.seed), "--wait-plc",
                "--truth-log", truth_path, "--port", str(port), "--calibration", args.calibration]
    command += ["--sim-oracle"] if args.sim_oracle else ["--models", args.models]
    if args.sim_parts:
        command += ["--sim-parts", args.sim_parts]
    print("running:", " ".join(command), flush=True)
    log = open(log_path, "w", encoding="utf-8")
    process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    problems = Problems()
    deadline = time.monotonic() + args.timeout
    started = time.monotonic()

    # Wait for the server.
    while time.monotonic() < deadline:
        if process.poll() is not None:
            log.close()
            print(open(log_path, encoding="utf-8").read())
            print(f"test_run_plc: cellsight exited with {process.returncode} before serving")
            return 1
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            break
        except OSError:
            time.sleep(0.1)

    shared = Shared(args.parts)
    shared.a_re_presented = 0
    shared.a_reconnected = False
    shared.abuse_answered = 0
    threads = [
        threading.Thread(target=plc_b, args=(port, shared, problems, deadline)),
        threading.Thread(target=plc_a, args=(port, shared, problems, deadline, args.reconnect_at)),
        threading.Thread(target=abuser, args=(port, shared, problems, 3)),
    ]
    for t in threads:
        t.start()
    threads[1].join(max(0.0, deadline - time.monotonic()))
    shared.stop = True
    with shared.cond:
        shared.cond.notify_all()
    for t in threads:
        t.join(10)

    # With --wait-plc and --parts, cellsight exits by itself once the PLC has acknowledged every result.
    try:
        code = process.wait(timeout=30)
    except subprocess.TimeoutExpired:
        problems.add("cellsight did not exit after the PLC took every result; sending SIGTERM")
        process.send_signal(signal.SIGTERM)
        try:
            code = process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            code = process.wait()
            problems.add("cellsight ignored SIGTERM")
    log.close()
    elapsed = time.monotonic() - started
    if code != 0:
        problems.add(f"cellsight exited with {code} (log: {log_path})")

    # ---- the handshake ----
    taken = shared.taken_by_a
    if sorted(taken) != list(range(1, args.parts + 1)):
        problems.add(f"PLC A took sequence numbers {sorted(taken)}, expected 1..{args.parts}")
    if sorted(shared.seen_by_b) != sorted(taken):
        problems.add(f"PLC B saw {sorted(shared.seen_by_b)}, PLC A took {sorted(taken)}")
    for seq, block in taken.items():
        if shared.seen_by_b.get(seq, block) != block:
            problems.add(f"result {seq}: PLC B read {shared.seen_by_b[seq]}, PLC A read {block}")
    if not shared.a_reconnected:
        problems.add("PLC A never reconnected (fewer results than --reconnect-at?)")
    acq_ids = [taken[s]["acq_id"] for s in sorted(taken)]
    if acq_ids != sorted(set(acq_ids)):
        problems.add(f"acquisition ids not increasing: {acq_ids}")
    if shared.abuse_answered == 0:
        problems.add("the abuser got no exception reply at all")

    # ---- the pose and sigma registers (map version 2) ----
    # Values and sigmas need not be valid yet (the recogniser may not estimate every axis); their format must hold.
    published = {value: 0 for value, _ in AXES}
    published.update({sigma: 0 for _, sigma in AXES})
    for seq in sorted(taken):
        for what in pose_format_problems(taken[seq]):
            problems.add(f"result {seq}: {what}")
        for value, sigma in AXES:
            published[value] += taken[seq][value] != INVALID_S32
            published[sigma] += taken[seq][sigma] != INVALID_SIGMA

    # ---- against the simulator's truth ----
    truth, templates = {}, {}
    try:
        with open(truth_path, encoding="utf-8") as f:
            for line in f:
                entry = json.loads(line)
                if "template" in entry:
                    templates[entry["template"]] = entry
                else:
                    truth[entry["acq_id"]] = entry
    except OSError as error:
        problems.add(f"truth log: {error}")
    if args.models:
        for name, entry in templates.items():
            if expected_ids.get(name, entry["part_id"]) != entry["part_id"]:
                problems.add(f"{name}: manifest id {expected_ids.get(name)} but the run loaded {entry['part_id']}")
    counts = {}
    correct = 0
    untaught = 0
    pose_errors = []
    for seq in sorted(taken):
        block = taken[seq]
        counts[block["code"]] = counts.get(block["code"], 0) + 1
        t = truth.get(block["acq_id"])
        if t is None or t.get("pass") is None:
            problems.add(f"result {seq}: no truth for acquisition {block['acq_id']}")
            continue
        want_id = t.get("oracle_part_id") if args.sim_oracle else expected_ids.get(t["part"])
        if want_id is None:
            # A part that was never taught must come out "unknown part", never as another part.
            untaught += 1
            if block["code"] == CODE_UNKNOWN:
                correct += 1
            elif block["code"] == CODE_OK:
                problems.add(f"result {seq}: untaught part {t['part']} decided as part {block['part_id']}")
            continue
        if block["code"] != CODE_OK or block["part_id"] != want_id:
            continue
        correct += 1
        want_x, want_y, want_th = expected_pose(t["pose"], None if args.sim_oracle else templates.get(t["part"]),
                                                template_poses.get(t["part"]))
        dx_mm = block["x_um"] / 1000.0 - want_x * 1000.0
        dy_mm = block["y_um"] / 1000.0 - want_y * 1000.0
        dth_deg = block["rz_mdeg"] / 1000.0 - want_th
        pose_errors.append((abs(dx_mm), abs(dy_mm), abs(dth_deg)))
        if args.sim_oracle:
            # The oracle publishes the truth on all six axes (run_sim.cpp): Z, RX, RY reach the PLC to the wire's
            # resolution, signs and word order included; it has no uncertainty, so every sigma is 0xFFFF.
            truth_zrr = ((t["pose"]["z_m"] * 1e6, "z_um"), (t["pose"]["tilt_deg"] * 1e3, "rx_mdeg"),
                         (t["pose"]["swing_deg"] * 1e3, "ry_mdeg"))
            for want, key in truth_zrr:
                if block[key] == INVALID_S32 or abs(block[key] - want) > 1.0:
                    problems.add(f"result {seq} ({t['part']}): {key} {block[key]} but the truth is {want:.1f}")
            if any(block[sigma] != INVALID_SIGMA for _, sigma in AXES):
                problems.add(f"result {seq}: the oracle has no sigma, yet a sigma register is not 0xFFFF")
        if abs(dx_mm) > args.pose_tol_mm or abs(dy_mm) > args.pose_tol_mm or abs(dth_deg) > args.theta_tol_deg:
            problems.add(f"result {seq} ({t['part']}): pose off by x {dx_mm:+.2f} mm, y {dy_mm:+.2f} mm, "
                         f"theta {dth_deg:+.3f} deg")
    if args.sim_oracle and pose_errors and max(max(e) for e in pose_errors) > 0.0011:
        problems.add("with --sim-oracle the pose must be the truth to the wire's resolution (1 um, 1 mdeg)")
    share = correct / len(taken) if taken else 0.0
    if share < args.min_correct:
        problems.add(f"{correct} of {len(taken)} parts ok with the true id ({share:.2%} < {args.min_correct:.0%})")

    summary = {
        "parts": args.parts, "taken_by_a": len(taken), "seen_by_b": len(shared.seen_by_b),
        "re_presented_after_reconnect": shared.a_re_presented, "exceptions_answered": shared.abuse_answered,
        "codes": counts, "correct": correct, "untaught": untaught, "valid_pose_registers": published,
        "max_pose_error": {"x_mm": max((e[0] for e in pose_errors), default=None),
                           "y_mm": max((e[1] for e in pose_errors), default=None),
                           "theta_deg": max((e[2] for e in pose_errors), default=None)},
        "cycle_ms": {"median": sorted(b["cycle_ms"] for b in taken.values())[len(taken) // 2] if taken else None,
                     "max": max((b["cycle_ms"] for b in taken.values()), default=None)},
        "exit_code": code, "seconds": round(elapsed, 1), "problems": len(problems.items), "work": work,
    }
    print(json.dumps(summary), flush=True)
    if problems.items:
        print(f"test_run_plc: FAILED; cellsight's log and the truth are in {work}")
        return 1
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
