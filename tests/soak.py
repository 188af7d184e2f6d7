#!/usr/bin/python3
"""Soak and fault-injection test of `cellsight run --sim` (issue 15), checked against the simulator's truth.

Phases (each checked; exit 0 only when every check holds):
  restart   SIGTERM mid-pass: `run --sim --wait-plc` is stopped with SIGTERM while a part is being scanned, --restarts
            times, and started again on the same port. cellsight must exit 0 within 10 s; the PLC sees the restart
            honestly (connection lost, then RESULT_SEQ 0 and no RESULT_VALID until a new result; the sequence starts
            at 1 again); the part in flight gets no result and the PLC can name it (TRIGGER_COUNT - results taken);
            every result it did take matches the truth.
  main      one `run --sim --wait-plc --parts N --sim-faults SPEC` process, while
              PLC A   follows the README's handshake (RESULT_VALID, one FC03 of 35 registers, both sequence copies,
                      RESULT_ACK, wait for RESULT_VALID to drop, clear the ack) and acknowledges every result; it
                      never pulses CLEAR_ERROR, so every recovery is the cell's own;
              PLC B   only polls status and result block with FC04;
              viewer  an operator's browser on the screen (HMI): live stream and status, every result the PLC
                      took must have been streamed with the same acquisition and part;
              abuser  malformed frames and forbidden requests (exception replies), broken framing, idle
                      connections held open, half frames (slowloris) and reconnect storms;
              sampler RSS (VmRSS) and open fds of the cellsight process from /proc after every result;
              teach   with --disk-full, `cellsight teach` into a copy of the model database on a small tmpfs (a
                      private mount namespace) that runs full at a scan, at the template and at the manifest: each
                      fails with a clear "No space left on device", the database stays as it was (manifest byte for
                      byte, `parts list` clean), and with room again the same teach succeeds.
            Checks: every part the simulated conveyor fed has exactly one result at the PLC, in order (truth pass
            indices 0..N-1, RESULT_SEQ 1..N, no gap, duplicate or torn block); results of passes with an aborting
            fault (camera_stall, encoder_glitch) are "bad scan" with no part id, the others the truth's part and
            pose (oracle) or the taught part or "unknown" (recogniser, wrong ids counted); ERROR_CODE episodes seen
            by the PLC match the injected faults one for one, RESULT_VALID is never set while ERROR is, no result's
            TIMESTAMP is older than the previous; 0 timeouts and late decisions (the loop's own counters), 0 missed
            triggers, the bounces filtered equal the bounces injected; RSS and non-socket fds of the first window of
            parts after 250 (the screen's bounded buffers fill until part 200) and the last window (1000 parts, or
            N/5 when N < 5000) within 1 %, sockets never above max_clients + 1 + the HMI's
            listener and the viewer's two connections.
Prints one JSON summary (and one line per problem); --json FILE writes it too.

usage: soak.py --cellsight BIN --config FILE --calibration FILE (--models DIR | --sim-oracle) [--parts N]
               [--faults SPEC] [--restarts K] [--disk-full] [--seed S] [--sim-parts A,B] [--keep DIR]
"""

import argparse
import http.client
import json
import os
import re
import shutil
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time

SCREEN_WARM_UP_PARTS = 250  # parts before the first memory window (see the RSS check)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
try:
    from pymodbus.client import ModbusTcpClient
    from pymodbus.exceptions import ModbusException
    import test_run_plc as plc_test
except ImportError as error:  # pragma: no cover - reported as "cannot run"
    print(f"soak: pymodbus 3 is needed (apt install python3-pymodbus python3-serial-asyncio): {error}")
    sys.exit(2)

# Register map (README "PLC interface"): literal on purpose, this is the PLC's view.
CONTROL, PLC_HEARTBEAT, STATUS, RESULT, RESULT_COUNT = 0, 4, 100, 200, 35  # result block of map version 2
TRIGGER_ENABLE, RESULT_ACK = 1 << 0, 1 << 2
TRIGGER_ACK, BUSY, RESULT_VALID, RESULT_OVERRUN, ERROR = 1 << 2, 1 << 3, 1 << 4, 1 << 5, 1 << 6
CODE_OK, CODE_UNKNOWN, CODE_BAD_SCAN, CODE_TIMEOUT = 0, 2, 5, 6
ERROR_CAMERA_TIMEOUT, ERROR_ENCODER = 2, 4
UNIT = 1
ABORTING = {"camera_stall": ERROR_CAMERA_TIMEOUT, "encoder_glitch": ERROR_ENCODER}
DEFAULT_FAULTS = "camera_stall@97,encoder_glitch@89,camera_hiccup@71,chatter@13"
PLC_PERIOD_S = 0.005  # PLC A's cycle; B polls at 4x that
LINK_ERRORS = (ConnectionError, OSError, ModbusException)


def u32(regs, i):
    return (regs[i] << 16) | regs[i + 1]


class Problems(plc_test.Problems):
    pass


# ------------------------------------------------------------------------------------------------ the process


class Cell:
    """One `cellsight run --sim` process."""

    def __init__(self, args, work, name, parts, port, seed, faults=""):
        self.log_path = os.path.join(work, f"{name}.log")
        self.truth_path = os.path.join(work, f"{name}.truth.jsonl")
        command = [args.cellsight, "--config", args.config, "run", "--sim", "--parts", str(parts), "--seed",
                   str(seed), "--wait-plc", "--truth-log", self.truth_path, "--port", str(port), "--calibration",
                   args.calibration]
        # The operator's screen runs as in production, on a port of its own (8080 may be taken on a CI machine).
        self.hmi_port = plc_test.free_port()
        command += ["--hmi-port", str(self.hmi_port)]
        command += ["--sim-oracle"] if args.sim_oracle else ["--models", args.models]
        if args.sim_parts:
            command += ["--sim-parts", args.sim_parts]
        if faults:
            command += ["--sim-faults", faults]
        if args.replay > 0:
            command += ["--sim-replay", str(args.replay)]
        self.command = command
        self.log = open(self.log_path, "w", encoding="utf-8")
        self.process = subprocess.Popen(command, stdout=self.log, stderr=subprocess.STDOUT)
        self.pid = self.process.pid
        self.port = port

    def wait_serving(self, timeout=120):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                return False
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.5).close()
                return True
            except OSError:
                time.sleep(0.05)
        return False

    def wait(self, timeout):
        try:
            return self.process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None
        finally:
            if self.process.poll() is not None and not self.log.closed:
                self.log.close()

    def kill(self):
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        if not self.log.closed:
            self.log.close()

    def log_text(self):
        with open(self.log_path, encoding="utf-8", errors="replace") as f:
            return f.read()

    def truth(self):
        """acq_id -> truth line (template lines left out)."""
        out = {}
        if os.path.exists(self.truth_path):
            with open(self.truth_path, encoding="utf-8") as f:
                for line in f:
                    entry = json.loads(line)
                    if "acq_id" in entry:
                        out[entry["acq_id"]] = entry
        return out


STOPPED_RE = re.compile(
    r"stopped after ([\d.]+) s: (\d+) parts, (\d+) results \((\d+) timeouts, (\d+) late decisions, (\d+) aborted "
    r"scans, (\d+) rejected\), (\d+) faults \((\d+) recovered\), (\d+) missed triggers, max cycle ([\d.]+) ms; "
    r"PLC: (\d+) presented, (\d+) acknowledged.*Modbus clients: (\d+) accepted, (\d+) evicted, (\d+) refused, "
    r"(\d+) dropped")
SIMLINE_RE = re.compile(r"simulated line: (\d+) passes started, (\d+) fed, (\d+) part-present bounces filtered")
PART_RE = re.compile(r" INFO loop: acq (\d+) (.+?): part .* cycle ([\d.]+) ms \(recognition ([\d.]+) ms\)")


def final_counters(text):
    m = STOPPED_RE.search(text)
    if not m:
        return None
    keys = ["seconds", "triggers", "results", "timeouts", "late_decisions", "aborted_scans", "rejected", "faults",
            "recovered", "missed_triggers", "max_cycle_ms", "presented", "acknowledged", "clients_accepted",
            "clients_evicted", "clients_refused", "clients_dropped"]
    out = {k: float(v) if "." in v else int(v) for k, v in zip(keys, m.groups())}
    s = SIMLINE_RE.search(text)
    if s:
        out["passes_started"], out["passes_fed"], out["bounces_filtered"] = (int(x) for x in s.groups())
    return out


def proc_sample(pid):
    """(VmRSS, RssAnon, RssFile, RssShmem in kB, non-socket fds, socket fds) of a process, or None when it is gone.

    RssAnon is the heap and the stacks (where a leak shows), RssFile the mapped files (templates, libraries),
    RssShmem the simulated cell's frame memo (--sim-replay), allocated up front."""
    try:
        fields = {}
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            for line in f:
                if line.startswith(("VmRSS:", "RssAnon:", "RssFile:", "RssShmem:")):
                    fields[line.split(":")[0]] = int(line.split()[1])
        sockets = others = 0
        for fd in os.listdir(f"/proc/{pid}/fd"):
            try:
                target = os.readlink(f"/proc/{pid}/fd/{fd}")
            except OSError:
                continue
            if target.startswith("socket:"):
                sockets += 1
            else:
                others += 1
        return (fields["VmRSS"], fields["RssAnon"], fields["RssFile"], fields["RssShmem"], others, sockets)
    except (OSError, KeyError):
        return None


# ------------------------------------------------------------------------------------------------ PLC A


class PlcA:
    """The PLC program of the README's worked example, acknowledging every result, never clearing errors itself."""

    def __init__(self, port, problems, name="PLC A"):
        self.port = port
        self.problems = problems
        self.name = name
        self.client = None
        self.heartbeat = 0
        self.ack_raised = False
        self.last_seq = 0
        self.last_timestamp = 0
        self.results = []          # (seq, block, status word, monotonic time)
        self.episodes = []         # [error code, t_start, t_end or None, results taken at start]
        self.status = None         # last status registers
        self.reconnects = 0
        self.torn = 0
        self.valid_with_error = 0
        self.on_result = None      # callback(block)

    def connect(self, attempts=50):
        for _ in range(attempts):
            client = ModbusTcpClient("127.0.0.1", port=self.port, timeout=3, retries=0)
            if client.connect():
                self.client = client
                return True
            time.sleep(0.1)
        return False

    def close(self):
        if self.client is not None:
            self.client.close()
            self.client = None

    def _write(self, address, value):
        if not plc_test.ok(self.client.write_register(address, value, slave=UNIT)):
            raise ConnectionError(f"write {address}={value} failed")

    def _read(self, address, count):
        rr = self.client.read_holding_registers(address, count, slave=UNIT)
        if not plc_test.ok(rr):
            raise ConnectionError(f"read {address}+{count} failed: {rr}")
        return rr.registers

    def cycle(self):
        """One PLC cycle; returns the status registers. Raises ConnectionError when the link is lost."""
        self.heartbeat = (self.heartbeat + 1) & 0xFFFF
        self._write(PLC_HEARTBEAT, self.heartbeat)
        st = self._read(STATUS, 11)
        self.status = st
        word, error_code = st[0], st[2]
        now = time.monotonic()
        if bool(word & ERROR) != (error_code != 0):
            self.problems.add(f"{self.name}: STATUS.ERROR {bool(word & ERROR)} but ERROR_CODE {error_code}")
        if word & RESULT_VALID and word & ERROR:
            self.valid_with_error += 1
            self.problems.add(f"{self.name}: RESULT_VALID set while ERROR (code {error_code}) is set")
        open_episode = self.episodes and self.episodes[-1][2] is None
        if error_code and not open_episode:
            self.episodes.append([error_code, now, None, len(self.results)])
        elif error_code and open_episode and self.episodes[-1][0] != error_code:
            self.episodes[-1][2] = now
            self.episodes.append([error_code, now, None, len(self.results)])
        elif not error_code and open_episode:
            self.episodes[-1][2] = now
        if word & RESULT_OVERRUN:
            self.problems.add(f"{self.name}: RESULT_OVERRUN (a result was lost)")
        if self.ack_raised:
            if not word & RESULT_VALID:
                self._write(CONTROL, TRIGGER_ENABLE)
                self.ack_raised = False
            return st
        if word & RESULT_VALID:
            regs = self._read(RESULT, RESULT_COUNT)
            block = plc_test.decode(regs)
            if not plc_test.whole(block):
                self.torn += 1
                self.problems.add(
                    f"{self.name}: torn block {block['seq']} / {block['seq_copy']} / {block['seq_copy2']}")
                return st
            if block["seq"] == self.last_seq:
                # Shown again after a reconnect or a fault with the same sequence: already taken, only acknowledge.
                self._write(CONTROL, TRIGGER_ENABLE | RESULT_ACK)
                self.ack_raised = True
                return st
            if block["seq"] != self.last_seq + 1:
                self.problems.add(f"{self.name}: sequence jumped from {self.last_seq} to {block['seq']}")
            if block["timestamp_us"] < self.last_timestamp:
                self.problems.add(f"{self.name}: result {block['seq']} is older than the one before it")
            self.last_seq = block["seq"]
            self.last_timestamp = block["timestamp_us"]
            self.results.append((block["seq"], block, word, now))
            if self.on_result:
                self.on_result(block)
            self._write(CONTROL, TRIGGER_ENABLE | RESULT_ACK)
            self.ack_raised = True
        return st

    def start(self):
        self._write(CONTROL, TRIGGER_ENABLE)
        self.ack_raised = False

    def run(self, want, deadline, stop, reconnect=True):
        """Cycles until `want` results, the deadline or stop(); reconnects when the server drops it."""
        while len(self.results) < want and time.monotonic() < deadline and not stop():
            try:
                self.cycle()
            except LINK_ERRORS as error:
                if not reconnect:
                    raise
                self.close()
                self.reconnects += 1
                print(f"{self.name}: link lost ({error}); reconnecting", flush=True)
                if not self.connect():
                    self.problems.add(f"{self.name}: cannot reconnect")
                    return
                self.ack_raised = False
                self.start()
                continue
            time.sleep(PLC_PERIOD_S)


# ------------------------------------------------------------------------------------------------ PLC B, abuser


def plc_b(port, shared, problems):
    """Polls with FC04 and never writes: checks what any reader sees."""
    client = ModbusTcpClient("127.0.0.1", port=port, timeout=3, retries=0)
    if not client.connect():
        problems.add("PLC B cannot connect")
        return
    last = 0
    try:
        while not shared.stop:
            try:
                st = client.read_input_registers(STATUS, 11, slave=UNIT)
                rr = client.read_input_registers(RESULT, RESULT_COUNT, slave=UNIT)
                if not plc_test.ok(st) or not plc_test.ok(rr):
                    raise ConnectionError(f"read failed: {st} {rr}")
            except LINK_ERRORS:
                shared.b_reconnects += 1
                client.close()
                time.sleep(0.1)
                client = ModbusTcpClient("127.0.0.1", port=port, timeout=3, retries=0)
                client.connect()
                continue
            shared.b_polls += 1
            if st.registers[0] & RESULT_VALID and st.registers[0] & ERROR:
                problems.add("PLC B: RESULT_VALID set while ERROR is set")
            block = plc_test.decode(rr.registers)
            if not plc_test.whole(block):
                problems.add(f"PLC B: torn block {block['seq']} / {block['seq_copy']} / {block['seq_copy2']}")
            elif block["seq"] < last:
                problems.add(f"PLC B: RESULT_SEQ went back from {last} to {block['seq']}")
            elif block["seq"] > last:
                shared.b_seen += 1
                last = block["seq"]
            time.sleep(4 * PLC_PERIOD_S)
    finally:
        client.close()


class RoundProblems:
    """Problems of one abuse round, kept only if the run was not over when the round ended: cellsight closes its port
    and exits by itself once the PLC has every result, and a round overlapping that sees refused connections."""

    def __init__(self):
        self.items = []

    def add(self, what):
        self.items.append(what)


def hmi_viewer(hmi_port, shared, problems):
    """An operator's browser on 127.0.0.1 (no login there): the live stream open all run, the status polled every
    2 s. Collects every streamed result {seq: result} into shared.hmi_results for the check against the PLC's."""
    shared.hmi_results, shared.hmi_status_polls, shared.hmi_reconnects = {}, 0, 0
    last_id, next_poll = 0, 0.0
    while not shared.stop:
        try:
            stream = http.client.HTTPConnection("127.0.0.1", hmi_port, timeout=2)
            stream.request("GET", "/api/events", headers={"Last-Event-ID": str(last_id)} if last_id else {})
            reply = stream.getresponse()
            if reply.status != 200:
                problems.add(f"HMI viewer: /api/events answered {reply.status}")
                return
            event = None
            while not shared.stop:
                if time.monotonic() >= next_poll:
                    poll = http.client.HTTPConnection("127.0.0.1", hmi_port, timeout=2)
                    poll.request("GET", "/api/status")
                    answer = poll.getresponse()
                    json.loads(answer.read())
                    poll.close()
                    if answer.status != 200:
                        problems.add(f"HMI viewer: /api/status answered {answer.status}")
                    shared.hmi_status_polls += 1
                    next_poll = time.monotonic() + 2.0
                try:
                    line = reply.fp.readline().decode()
                except socket.timeout:
                    continue
                if not line:
                    raise ConnectionError("the live stream ended")
                if line.startswith("event: "):
                    event = line[7:].strip()
                elif line.startswith("id: "):
                    last_id = int(line[4:])
                elif line.startswith("data: ") and event == "result":
                    result = json.loads(line[6:])
                    shared.hmi_results[result["seq"]] = result
            stream.close()
        except (OSError, ConnectionError, http.client.HTTPException, ValueError):
            if shared.stop:
                break
            shared.hmi_reconnects += 1
            time.sleep(0.5)


def check_hmi_view(shared, plc, problems, summary):
    """Every result the PLC took was streamed to the screen once, with the same part, code and acquisition."""
    seen = getattr(shared, "hmi_results", {})
    missing = wrong = 0
    for seq, block, _, _ in plc.results:
        shown = seen.get(seq)
        if shown is None:
            missing += 1
        elif shown["acq_id"] != block["acq_id"] or shown["part_id"] != block["part_id"]:
            wrong += 1
    summary["hmi"] = {"streamed": len(seen), "missing": missing, "different": wrong,
                      "status_polls": getattr(shared, "hmi_status_polls", 0),
                      "stream_reconnects": getattr(shared, "hmi_reconnects", 0)}
    if missing or wrong:
        problems.add(f"HMI viewer: of {len(plc.results)} results {missing} never streamed, {wrong} differ from the PLC's")
    if getattr(shared, "hmi_status_polls", 0) == 0:
        problems.add("HMI viewer: no status poll answered")


def abuser(port, shared, problems):
    """Rounds of abuse, one every couple of seconds, until stopped or the run is over."""
    rounds = 0
    while not shared.stop and not shared.run_over():
        rounds += 1
        found = RoundProblems()
        abuse_round(port, shared, found)
        if shared.run_over():
            break
        for what in found.items:
            problems.add(what)
    shared.abuse_rounds = rounds


def abuse_round(port, shared, problems):
    """One round: exception cases, broken framing, idle connections, a half frame, a storm of connections."""
    # Exception replies and broken framing (test_run_plc's cases), one round.
    plc_test.abuser(port, shared, problems, 1)
    shared.abuse_answered_total += shared.abuse_answered
    # Idle connections held open: they may be evicted for a newcomer, never lock anybody out.
    idle = []
    for _ in range(3):
        try:
            idle.append(socket.create_connection(("127.0.0.1", port), timeout=2))
        except OSError as error:
            problems.add(f"abuser: cannot open an idle connection: {error}")
    # A half frame (slowloris): dropped after modbus.byte_timeout_ms.
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=3) as s:
            s.sendall(plc_test.mbap(1, struct.pack(">BHH", 0x03, RESULT, RESULT_COUNT))[:5])
            s.settimeout(3)
            if s.recv(16) != b"":
                problems.add("abuser: a half frame got an answer instead of a closed connection")
            shared.slowloris_closed += 1
    except socket.timeout:
        problems.add("abuser: a half frame kept its connection for 3 s")
    except OSError:
        shared.slowloris_closed += 1
    # A reconnect storm.
    for _ in range(20):
        try:
            socket.create_connection(("127.0.0.1", port), timeout=2).close()
            shared.storm_connects += 1
        except OSError as error:
            problems.add(f"abuser: storm connection refused: {error}")
    for _ in range(40):  # hold the idle ones a couple of seconds
        if shared.stop:
            break
        time.sleep(0.05)
    for s in idle:
        s.close()


# ------------------------------------------------------------------------------------------------ disk full


def disk_full_child(args):
    """Runs inside a private mount namespace (unshare -m): teach into a database on a small tmpfs."""
    report = {"attempts": [], "problems": []}

    def problem(what):
        report["problems"].append(what)

    mnt = tempfile.mkdtemp(prefix="cellsight_diskfull_")
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2g", "tmpfs", mnt]).returncode != 0:
        print(json.dumps({"skipped": "cannot mount a tmpfs"}))
        return 0
    models = os.path.join(mnt, "models")
    base = [args.cellsight, "--config", args.config, "--models", models, "--log-level", "warn"]
    teach = base + ["teach", "--part", args.teach_part, "--id", str(args.teach_id), "--sim", "--count",
                    str(args.teach_count), "--seed", "5", "--calibration", args.calibration]

    def used_bytes():
        st = os.statvfs(mnt)
        return (st.f_blocks - st.f_bfree) * st.f_frsize

    def remount(size):
        size = max(4096, (size + 4095) // 4096 * 4096)
        return subprocess.run(["mount", "-o", f"remount,size={size}", mnt]).returncode == 0

    def snapshot():
        files = {}
        for root, _, names in os.walk(models):
            for n in names:
                p = os.path.join(root, n)
                files[os.path.relpath(p, models)] = os.path.getsize(p)
        return files

    try:
        if args.models:
            shutil.copytree(args.models, models)
        else:
            first = subprocess.run(base + ["teach", "--part", args.first_part, "--id", "1", "--sim", "--count", "2",
                                           "--calibration", args.calibration], capture_output=True, text=True)
            if first.returncode != 0:
                problem(f"the first teach into an empty database failed: {first.stdout}{first.stderr}")
                return 0
        with open(os.path.join(models, "manifest.yaml"), "rb") as f:
            manifest_before = f.read()
        before = snapshot()
        # How much the teach writes, measured by doing it once with room, then undone (the copy restored).
        saved = os.path.join(mnt, "saved")
        shutil.copytree(models, saved)
        base_used = used_bytes()
        full = subprocess.run(teach, capture_output=True, text=True)
        if full.returncode != 0:
            problem(f"the teach with room failed: {full.stdout}{full.stderr}")
            return 0
        after = snapshot()
        added = {k: v for k, v in after.items() if before.get(k) != v and k != "manifest.yaml"}
        shutil.rmtree(models)
        shutil.move(saved, models)
        pages = sum((v + 4095) // 4096 * 4096 for v in added.values())
        report["teach_writes_bytes"] = {"files": len(added), "bytes": sum(added.values()), "pages_bytes": pages}
        # Free space: a few pages (the first file written fails), room for the largest file (the template) and a
        # few pages (a file after it fails), room for everything but the manifest.
        largest = max((v + 4095) // 4096 * 4096 for v in added.values())
        points = [("start", 16384), ("after the largest file", largest + 16384), ("manifest", pages)]
        for where, free in points:
            base_used = used_bytes()
            if not remount(base_used + max(0, free)):
                problem("cannot remount the tmpfs smaller")
                break
            r = subprocess.run(teach, capture_output=True, text=True)
            text = r.stdout + r.stderr
            attempt = {"full_at": where, "free_bytes": free, "exit": r.returncode,
                       "message": next((l for l in text.splitlines() if "No space" in l), text.strip()[-300:])}
            if where == "manifest" and "manifest.yaml" not in attempt["message"]:
                problem(f"disk full with room for all but the manifest: the failure names another file: "
                        f"{attempt['message']}")
            report["attempts"].append(attempt)
            if r.returncode == 0:
                problem(f"disk full at the {where}: the teach succeeded with {free} bytes free")
            if "No space left on device" not in text:
                problem(f"disk full at the {where}: the message does not say so: {text.strip()[-300:]}")
            with open(os.path.join(models, "manifest.yaml"), "rb") as f:
                if f.read() != manifest_before:
                    problem(f"disk full at the {where}: manifest.yaml changed")
            temps = [k for k in snapshot() if re.search(r"\.tmp-[A-Za-z0-9]{6}$", k)]
            if temps:
                problem(f"disk full at the {where}: temporary files left: {temps}")
            remount(2 << 30)
            listing = subprocess.run(base + ["parts", "list"], capture_output=True, text=True)
            attempt["parts_list_exit"] = listing.returncode
            if listing.returncode != 0 or args.teach_part + " " in listing.stdout:
                problem(f"disk full at the {where}: parts list after it: exit {listing.returncode}: "
                        f"{listing.stdout[-400:]}{listing.stderr[-400:]}")
        # Room again: the same teach succeeds (and sweeps what the failed ones left).
        r = subprocess.run(teach, capture_output=True, text=True)
        report["teach_with_room_again_exit"] = r.returncode
        listing = subprocess.run(base + ["parts", "list"], capture_output=True, text=True)
        if r.returncode != 0 or listing.returncode != 0 or args.teach_part not in listing.stdout:
            problem(f"with room again the teach did not succeed: {r.stdout[-300:]}{r.stderr[-300:]}")
    finally:
        subprocess.run(["umount", mnt])
        os.rmdir(mnt)
        print(json.dumps(report), flush=True)
    return 0


def disk_full(args, problems, results):
    command = ["unshare", "-m", sys.executable, os.path.abspath(__file__), "--disk-full-child",
               "--cellsight", args.cellsight, "--config", args.config, "--calibration", args.calibration,
               "--teach-part", args.teach_part, "--teach-id", str(args.teach_id), "--teach-count",
               str(args.teach_count), "--first-part", args.first_part]
    command += ["--models", args.models] if args.models else ["--sim-oracle"]
    r = subprocess.run(command, capture_output=True, text=True)
    if r.returncode != 0 and not r.stdout.strip() and "unshare" in r.stderr:
        # No private mount namespace here (not root, or a container without CAP_SYS_ADMIN): said, not hidden.
        print(f"soak: disk-full teach SKIPPED: {r.stderr.strip()}", flush=True)
        results.append({"skipped": r.stderr.strip()})
        return
    try:
        report = json.loads(r.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        problems.add(f"disk full: no report (exit {r.returncode}): {r.stdout[-500:]}{r.stderr[-500:]}")
        return
    for p in report.pop("problems", []):
        problems.add(f"disk full: {p}")
    results.append(report)


# ------------------------------------------------------------------------------------------------ phases


def restart_phase(args, work, problems, summary):
    """SIGTERM mid-pass, --restarts times; then a run that completes."""
    port = plc_test.free_port()
    parts_per_run = 4
    out = {"cycles": 0, "exits": [], "stop_seconds": [], "interrupted_parts": 0, "results_taken": 0}
    plc = PlcA(port, problems, "PLC (restarts)")
    for cycle in range(args.restarts + 1):
        last = cycle == args.restarts
        cell = Cell(args, work, f"restart{cycle}", parts_per_run, port, args.seed + 1000 + cycle)
        if not cell.wait_serving():
            problems.add(f"restart {cycle}: cellsight did not serve: {cell.log_text()[-800:]}")
            cell.kill()
            return out
        if not plc.connect():
            problems.add(f"restart {cycle}: the PLC cannot connect")
            cell.kill()
            return out
        plc.results, plc.last_seq, plc.last_timestamp, plc.ack_raised = [], 0, 0, False
        # The restart as the PLC sees it: no result, no RESULT_VALID, counters back to 0.
        first = plc._read(STATUS, 11)
        block = plc_test.decode(plc._read(RESULT, RESULT_COUNT))
        if cycle > 0 and (block["seq"] != 0 or first[0] & RESULT_VALID or u32(first, 5) != 0):
            problems.add(f"restart {cycle}: after the restart RESULT_SEQ {block['seq']}, STATUS {first[0]:#06x}, "
                         f"TRIGGER_COUNT {u32(first, 5)}: an old result or count looks fresh")
        plc.start()
        deadline = time.monotonic() + 600
        if last:
            plc.run(parts_per_run, deadline, lambda: False, reconnect=False)
            code = cell.wait(60)
            out["exits"].append(code)
            if code != 0:
                problems.add(f"restart {cycle}: the final run exited {code}")
        else:
            # Take one result, then stop the cell while the next part is being scanned.
            stopped_at = None
            seen_acq = 0
            while time.monotonic() < deadline:
                st = plc.cycle()
                seen_acq = u32(st, 5)
                if plc.results and st[0] & (BUSY | TRIGGER_ACK) and seen_acq > len(plc.results):
                    cell.process.send_signal(signal.SIGTERM)
                    stopped_at = time.monotonic()
                    break
                time.sleep(PLC_PERIOD_S)
            if stopped_at is None:
                problems.add(f"restart {cycle}: never saw a pass in progress to stop")
                cell.kill()
                return out
            # The PLC keeps polling: it must lose the link, and it knows which part got no result.
            taken_before = len(plc.results)
            try:
                for _ in range(3000):
                    plc.cycle()
                    time.sleep(PLC_PERIOD_S)
            except LINK_ERRORS:
                pass
            code = cell.wait(10)
            elapsed = time.monotonic() - stopped_at
            out["exits"].append(code)
            out["stop_seconds"].append(round(elapsed, 2))
            if code is None:
                problems.add(f"restart {cycle}: cellsight still running 10 s after SIGTERM")
                cell.kill()
            elif code != 0:
                problems.add(f"restart {cycle}: cellsight exited {code} after SIGTERM")
            if "SIGTERM: stopping" not in cell.log_text():
                problems.add(f"restart {cycle}: no 'SIGTERM: stopping' in the log")
            interrupted = seen_acq - len(plc.results)
            out["interrupted_parts"] += interrupted
            if interrupted < 1:
                problems.add(f"restart {cycle}: SIGTERM mid-pass but every started pass has a result")
            if len(plc.results) != taken_before:
                # A result that appeared after SIGTERM belongs to the interrupted part's neighbours: fine if in
                # sequence, which cycle() checked.
                pass
        plc.close()
        out["cycles"] += 1
        out["results_taken"] += len(plc.results)
        truth = cell.truth()
        for seq, block, _, _ in plc.results:
            t = truth.get(block["acq_id"])
            if t is None or t.get("pass") is None:
                problems.add(f"restart {cycle}: result {seq} (acq {block['acq_id']}) has no truth")
            elif args.sim_oracle and (block["code"] != CODE_OK or block["part_id"] != t["oracle_part_id"]):
                problems.add(f"restart {cycle}: result {seq} is not the truth's part")
        if [b["acq_id"] for _, b, _, _ in plc.results] != list(range(1, len(plc.results) + 1)):
            problems.add(f"restart {cycle}: acquisition ids of the results are not 1..n")
    summary["restart"] = out


def percentile(values, p):
    if not values:
        return None
    s = sorted(values)
    k = min(len(s) - 1, max(0, int(round(p / 100.0 * (len(s) - 1)))))
    return s[k]


def main_phase(args, work, problems, summary):
    port = plc_test.free_port()
    cell = Cell(args, work, "main", args.parts, port, args.seed, args.faults)
    if not cell.wait_serving():
        problems.add(f"main: cellsight did not serve: {cell.log_text()[-2000:]}")
        cell.kill()
        return
    shared = plc_test.Shared(args.parts)
    shared.abuse_answered = shared.abuse_answered_total = shared.abuse_rounds = 0
    shared.b_polls = shared.b_seen = shared.b_reconnects = 0
    shared.slowloris_closed = shared.storm_connects = 0
    plc = PlcA(port, problems)
    shared.run_over = lambda: len(plc.results) >= args.parts or cell.process.poll() is not None
    samples = []  # (results taken,) + proc_sample()
    disk_reports = []
    disk_at = set()
    if args.disk_full:
        disk_at = {max(1, args.parts // 3)} if args.parts < 3000 else {args.parts // 3, 2 * args.parts // 3}
    disk_threads = []

    def on_result(_block):
        n = len(plc.results)
        s = proc_sample(cell.pid)
        if s:
            samples.append((n,) + s)
        if n in disk_at:
            t = threading.Thread(target=disk_full, args=(args, problems, disk_reports))
            t.start()
            disk_threads.append(t)
        if n % 500 == 0:
            print(f"soak: {n} of {args.parts} results, RSS {s[0] if s else '?'} kB", flush=True)

    plc.on_result = on_result
    if not plc.connect():
        problems.add("main: PLC A cannot connect")
        cell.kill()
        return
    plc.start()
    threads = [threading.Thread(target=plc_b, args=(port, shared, problems)),
               threading.Thread(target=abuser, args=(port, shared, problems)),
               threading.Thread(target=hmi_viewer, args=(cell.hmi_port, shared, problems))]
    for t in threads:
        t.start()
    started = time.monotonic()
    try:
        plc.run(args.parts, started + args.timeout, lambda: cell.process.poll() is not None)
        # Keep cycling until cellsight has seen the last acknowledgement and exits.
        end = time.monotonic() + 30
        while cell.process.poll() is None and time.monotonic() < end:
            try:
                plc.cycle()
            except LINK_ERRORS:
                break
            time.sleep(PLC_PERIOD_S)
    finally:
        shared.stop = True
        for t in threads:
            t.join(30)
        for t in disk_threads:
            t.join(600)
        plc.close()
    code = cell.wait(30)
    elapsed = time.monotonic() - started
    if code is None:
        problems.add("main: cellsight did not exit after the PLC took every result")
        cell.kill()
    elif code != 0:
        problems.add(f"main: cellsight exited {code}")
    text = cell.log_text()
    counters = final_counters(text) or {}
    if not counters:
        problems.add("main: no final counters in cellsight's log")

    check_hmi_view(shared, plc, problems, summary)

    # ---- every part fed has exactly one result, in order ----
    truth = cell.truth()
    taken = plc.results
    seqs = [s for s, _, _, _ in taken]
    if seqs != list(range(1, args.parts + 1)):
        problems.add(f"main: PLC A took {len(seqs)} results, sequence 1..{args.parts} "
                     f"{'broken' if seqs[:len(seqs)] != list(range(1, len(seqs) + 1)) else 'incomplete'}")
    passes = []
    expected_fault = {}
    wrong_ids = unknown = correct = 0
    for seq, block, _, _ in taken:
        t = truth.get(block["acq_id"])
        if t is None or t.get("pass") is None:
            problems.add(f"main: result {seq} (acq {block['acq_id']}) has no truth")
            continue
        passes.append(t["pass"])
        fault = t.get("fault")
        if fault:
            expected_fault[fault] = expected_fault.get(fault, 0) + 1
        if fault in ABORTING:
            if block["code"] != CODE_BAD_SCAN or block["part_id"] != 0:
                problems.add(f"main: result {seq} ({fault}) is code {block['code']} part {block['part_id']}, "
                             f"expected bad scan and no part: a stale decision?")
            continue
        if block["code"] == CODE_TIMEOUT:
            continue  # counted below as a deadline miss
        if args.sim_oracle:
            if block["code"] != CODE_OK or block["part_id"] != t["oracle_part_id"]:
                problems.add(f"main: result {seq} ({fault or 'no fault'}) is code {block['code']} part "
                             f"{block['part_id']}, truth part {t['oracle_part_id']}")
            else:
                correct += 1
                want = (round(t["pose"]["x_m"] * 1e6), round(t["pose"]["y_m"] * 1e6),
                        round(t["pose"]["theta_deg"] * 1e3))
                got = (block["x_um"], block["y_um"], block["rz_mdeg"])
                if any(abs(a - b) > 1 for a, b in zip(want, got)):
                    problems.add(f"main: result {seq}: pose {got}, truth {want}")
        else:
            want_id = args.expected_ids.get(t["part"])
            if block["code"] == CODE_OK and block["part_id"] == want_id:
                correct += 1
            elif block["code"] == CODE_UNKNOWN:
                unknown += 1
            else:
                wrong_ids += 1
                problems.add(f"main: result {seq} ({t['part']}, {fault or 'no fault'}): code {block['code']} part "
                             f"{block['part_id']}, expected part {want_id}")
    if passes != list(range(len(passes))):
        gaps = sorted(set(range(max(passes, default=-1) + 1)) - set(passes))
        dups = len(passes) - len(set(passes))
        problems.add(f"main: the results' truth passes are not 0..{len(passes) - 1} in order: "
                     f"{len(gaps)} fed parts without a result {gaps[:10]}, {dups} duplicates")
    if counters and counters.get("passes_started") != args.parts:
        problems.add(f"main: the simulated line started {counters.get('passes_started')} passes for "
                     f"{args.parts} results")

    # ---- deadlines, missed triggers, codes ----
    codes = {}
    for _, b, _, _ in taken:
        codes[b["code"]] = codes.get(b["code"], 0) + 1
    deadline_misses = counters.get("timeouts", 0) + counters.get("late_decisions", 0)
    if deadline_misses or codes.get(CODE_TIMEOUT):
        problems.add(f"main: deadline misses: {counters.get('timeouts')} timeouts, "
                     f"{counters.get('late_decisions')} late decisions, {codes.get(CODE_TIMEOUT, 0)} timeout results")
    if counters.get("missed_triggers"):
        problems.add(f"main: {counters['missed_triggers']} missed triggers")
    if counters.get("rejected"):
        problems.add(f"main: {counters['rejected']} results rejected (queue full)")

    # ---- faults: told to the PLC, recovered by the cell itself ----
    episodes = [(e[0], (e[2] or time.monotonic()) - e[1]) for e in plc.episodes]
    by_code = {}
    for c, d in episodes:
        by_code.setdefault(c, []).append(d)
    fault_report = {}
    for kind in ("camera_stall", "encoder_glitch", "camera_hiccup", "chatter"):
        n = expected_fault.get(kind, 0)
        entry = {"injected": n}
        if kind in ABORTING:
            seen = by_code.get(ABORTING[kind], [])
            entry["error_episodes_seen"] = len(seen)
            entry["recovery_s_max"] = round(max(seen), 2) if seen else None
            entry["survived"] = min(n, len(seen)) if code == 0 else 0
            if len(seen) != n:
                problems.add(f"main: {n} {kind} faults but the PLC saw {len(seen)} ERROR_CODE "
                             f"{ABORTING[kind]} episodes")
        else:
            entry["survived"] = n if code == 0 else 0
        fault_report[kind] = entry
    other = {c: len(v) for c, v in by_code.items() if c not in ABORTING.values()}
    if other:
        problems.add(f"main: unexpected ERROR_CODE episodes {other}")
    if counters and counters.get("faults") != counters.get("recovered"):
        problems.add(f"main: {counters.get('faults')} faults, {counters.get('recovered')} recovered")
    aborting = sum(expected_fault.get(k, 0) for k in ABORTING)
    if counters and counters.get("faults") != aborting:
        problems.add(f"main: the loop counted {counters.get('faults')} faults, {aborting} aborting faults injected")
    chatter = expected_fault.get("chatter", 0)
    pairs = args.chatter_pairs
    injected = chatter * 2 * 2 * pairs  # pairs of raw edges after the rising and the falling edge
    last_truth = truth.get(taken[-1][1]["acq_id"]) if taken else None
    if last_truth and last_truth.get("fault") == "chatter":
        injected -= 2 * pairs  # the last part's falling-edge bounces come after the loop has taken its last part
    if counters and counters.get("bounces_filtered") != injected:
        problems.add(f"main: {counters.get('bounces_filtered')} bounces filtered, {injected} injected")
    fault_report["chatter"]["bounces_filtered"] = counters.get("bounces_filtered")

    # ---- memory and fds ----
    window = min(1000, max(1, args.parts // 5))
    # The first window starts after the operator's screen has filled its bounded buffers (200 results of history,
    # 16 live pictures, the review ring's list): they fill during the first 200 parts and then stay, which a window
    # from part 1 would read as growth. A leak keeps growing after that.
    warm_up = min(SCREEN_WARM_UP_PARTS, max(0, args.parts - 2 * window))
    first = [s for s in samples if warm_up < s[0] <= warm_up + window]
    last = [s for s in samples if s[0] > args.parts - window]
    mem_first_window = (warm_up + 1, warm_up + window)
    mem = {"window_parts": window, "first_window": mem_first_window, "samples": len(samples)}
    if first and last:
        for i, name in ((1, "vm_rss_kb"), (2, "rss_anon_kb"), (3, "rss_file_kb"), (4, "rss_shmem_kb"), (5, "fds")):
            f_med, l_med = statistics.median(s[i] for s in first), statistics.median(s[i] for s in last)
            f_max, l_max = max(s[i] for s in first), max(s[i] for s in last)
            mem[name] = {"first_median": f_med, "last_median": l_med, "first_max": f_max, "last_max": l_max,
                         "change_median_pct": round(100.0 * (l_med - f_med) / max(1, f_med), 3),
                         "change_max_pct": round(100.0 * (l_max - f_max) / max(1, f_max), 3)}
            if abs(l_med - f_med) > 0.01 * f_med or l_max > 1.01 * f_max:
                problems.add(f"main: {name} not flat: first {window} parts median {f_med} max {f_max}, last "
                             f"median {l_med} max {l_max}")
        mem["sockets_max"] = max(s[6] for s in samples)
        # Modbus: max_clients + its listener; the screen: its listener + the viewer's stream and status poll.
        if mem["sockets_max"] > args.max_clients + 1 + 3:
            problems.add(f"main: {mem['sockets_max']} sockets open (max_clients {args.max_clients} + listener, "
                         "HMI listener + 2 viewer connections)")
    else:
        problems.add("main: too few RSS/fd samples")

    # ---- cycle time (the loop's own log, 0.1 ms; CYCLE_MS cross-checked) ----
    cycles = {}
    for m in PART_RE.finditer(text):
        cycles[int(m.group(1))] = float(m.group(3))
    ok_cycles = [cycles[b["acq_id"]] for _, b, _, _ in taken if b["code"] != CODE_BAD_SCAN and b["acq_id"] in cycles]
    # CYCLE_MS is taken when the result is made, the log's cycle once the link took it: the register can only be
    # the shorter (by the hand-over, which a loaded machine stretches), never the longer.
    handover_ms = [0.0]
    for _, b, _, _ in taken:
        c = cycles.get(b["acq_id"])
        if c is None or b["code"] == CODE_BAD_SCAN:
            continue
        handover_ms.append(c - b["cycle_ms"])
        if b["cycle_ms"] > c + 0.5:
            problems.add(f"main: acq {b['acq_id']}: CYCLE_MS {b['cycle_ms']} but the log says {c} ms")
    summary["main"] = {
        "parts": args.parts, "results_taken": len(taken), "lost": args.parts - len(set(passes)),
        "deadline_misses": deadline_misses, "codes": {str(k): v for k, v in sorted(codes.items())},
        "correct": correct, "unknown": unknown, "wrong_ids": wrong_ids,
        "cycle_ms": {"p50": percentile(ok_cycles, 50), "p99": percentile(ok_cycles, 99),
                     "max": max(ok_cycles, default=None), "register_below_log_max": round(max(handover_ms), 1)},
        "faults": fault_report, "memory": mem,
        "plc_a": {"reconnects": plc.reconnects, "torn": plc.torn, "valid_with_error": plc.valid_with_error},
        "plc_b": {"polls": shared.b_polls, "results_seen": shared.b_seen, "reconnects": shared.b_reconnects},
        "abuser": {"rounds": shared.abuse_rounds, "exceptions_answered": shared.abuse_answered_total,
                   "half_frames_closed": shared.slowloris_closed, "storm_connects": shared.storm_connects},
        "cellsight": counters, "exit_code": code, "seconds": round(elapsed, 1),
        "parts_per_second": round(args.parts / elapsed, 3) if elapsed > 0 else None,
        "disk_full": disk_reports,
    }
    if args.disk_full and not disk_reports:
        problems.add("main: the disk-full teach did not report")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cellsight", required=True)
    parser.add_argument("--config", required=True)
    parser.add_argument("--calibration", required=True)
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--models", help="trained model database: the production recogniser decides")
    group.add_argument("--sim-oracle", action="store_true", help="decisions from the simulator's truth")
    parser.add_argument("--parts", type=int, default=500)
    parser.add_argument("--faults", default=DEFAULT_FAULTS, help="cellsight run --sim-faults SPEC")
    parser.add_argument("--chatter-pairs", type=int, default=3, help="bounce pairs per edge the SPEC gives chatter")
    parser.add_argument("--restarts", type=int, default=2, help="SIGTERM mid-pass, then restart, this many times")
    parser.add_argument("--disk-full", action="store_true", help="teach into a full tmpfs during the main run")
    parser.add_argument("--teach-part", default="channel_u")
    parser.add_argument("--teach-id", type=int, default=9)
    parser.add_argument("--teach-count", type=int, default=3)
    parser.add_argument("--first-part", default="plate_4h")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--sim-parts")
    parser.add_argument("--replay", type=int, default=12,
                        help="cellsight run --sim-replay K: K distinct passes, rendered once (0: render every pass)")
    parser.add_argument("--max-clients", type=int, default=4)
    parser.add_argument("--timeout", type=float, default=7 * 24 * 3600.0)
    parser.add_argument("--json", help="write the summary here too")
    parser.add_argument("--keep", help="keep logs and truth in this folder")
    parser.add_argument("--disk-full-child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.disk_full_child:
        return disk_full_child(args)
    if not os.access(args.cellsight, os.X_OK):
        print(f"soak: {args.cellsight} is not an executable")
        return 2
    args.expected_ids = {}
    if args.models:
        loaded, why = plc_test.load_manifest_ids(args.models)
        if loaded is None:
            print(f"soak: {why}")
            return 2
        args.expected_ids = loaded[0]
    work = args.keep or tempfile.mkdtemp(prefix="cellsight_soak_")
    os.makedirs(work, exist_ok=True)
    problems = Problems()
    summary = {"faults_spec": args.faults, "work": work}
    started = time.monotonic()
    if args.restarts > 0:
        restart_phase(args, work, problems, summary)
    main_phase(args, work, problems, summary)
    summary["seconds"] = round(time.monotonic() - started, 1)
    summary["problems"] = len(problems.items)
    text = json.dumps(summary, indent=1)
    print(text, flush=True)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            f.write(text + "\n")
    if problems.items:
        print(f"soak: FAILED ({len(problems.items)} problems); logs and truth in {work}")
        return 1
    print(f"soak: passed ({args.parts} parts)")
    if not args.keep:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
