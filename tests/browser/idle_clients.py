#!/usr/bin/env python3
"""Do idle browsers stop the PLC's results? (issue 14: "50 idle browsers do not stop the PLC results")

Starts `cellsight run --sim --wait-plc` on the simulated cell of scripts/sim_cell.sh with an acknowledging PLC
(tests/modbus_plc_client.py, which reports any gap in RESULT_SEQ) and measures four phases of --seconds each, asking /api/status every second throughout:
  quiet        no browser
  live views   --streams live streams asked for (GET /api/events; the server serves 3/4 of hmi.max_clients and
               answers 503 to the others), kept open and read
  + idle       and --idle TCP connections to the screen that send nothing (each one reopened when the server
               closes it, so the load stays on)
  after        the load closed again
and prints a table: the PLC's results (count, per second, gaps), the loop's cycle time per part (the cycle_ms the
PLC reads with each result: mean, 95th percentile, max), the streams served / refused / unanswered and the results
they carried, the idle connections the server closed, and how long /api/status took under the load.
Not a CI test (README "Operator's screen"): a figure for the README. Exit 1 when the PLC saw a gap or an error.

usage: tests/browser/idle_clients.py --cellsight BIN --cell DIR [--seconds S] [--idle N] [--streams N]
  (BIN: a Release build; DIR: scripts/sim_cell.sh's WORK/cell, e.g. build/soak/cell after tests/browser/run.sh)
"""

import argparse
import http.client
import json
import os
import selectors
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
SIM_PARTS = "plate_4h,plate_5h,bracket_l"  # the cell's taught parts (scripts/sim_cell.sh)
CONNECT_TIMEOUT_S = 5.0


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port, process, timeout_s=60.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if process.poll() is not None:
            sys.exit(f"idle_clients: cellsight exited ({process.returncode}) before port {port} listened")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            time.sleep(0.05)
    sys.exit(f"idle_clients: port {port} never listened")


class Plc:
    """The acknowledging PLC; every result with its arrival time and the loop's cycle_ms."""

    def __init__(self, port):
        self.results = []  # (monotonic time, seq, cycle_ms)
        self.errors = []
        self.process = subprocess.Popen(
            ["/usr/bin/python3", os.path.join(REPO, "tests", "modbus_plc_client.py"), "--port", str(port),
             "--count", "100000000", "--timeout", "36000"], stdout=subprocess.PIPE, text=True)
        self.thread = threading.Thread(target=self.read, daemon=True)
        self.thread.start()

    def read(self):
        for line in self.process.stdout:
            event = json.loads(line)
            if event["event"] == "result":
                self.results.append((time.monotonic(), event["seq"], event["cycle_ms"]))
            elif event["event"] == "error":
                self.errors.append(event["what"])

    def between(self, start, end):
        return [r for r in self.results if start <= r[0] < end]


class Stream(threading.Thread):
    """One live view: GET /api/events on a socket of its own, then counts the result events it is sent."""

    def __init__(self, port):
        super().__init__(daemon=True)
        self.port, self.status, self.results, self.stop = port, None, 0, threading.Event()
        self.sock = None

    def run(self):
        try:
            self.sock = socket.create_connection(("127.0.0.1", self.port), timeout=CONNECT_TIMEOUT_S)
            self.sock.sendall(f"GET /api/events HTTP/1.1\r\nHost: 127.0.0.1:{self.port}\r\n\r\n".encode())
            stream = self.sock.makefile("rb")
            status_line = stream.readline().split()
            self.status = int(status_line[1]) if len(status_line) > 1 else "no answer"
            if self.status != 200:
                return
            self.sock.settimeout(None)  # a status event comes every second; close() ends the read
            while not self.stop.is_set():
                line = stream.readline()
                if not line:
                    return
                if line.startswith(b"event: result"):
                    self.results += 1
        except OSError:
            if self.status is None:
                self.status = "no answer"

    def close(self):
        self.stop.set()
        if self.sock is not None:
            try:
                self.sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass


class IdleClients(threading.Thread):
    """N connections that send nothing; one the server closes is counted and opened again."""

    def __init__(self, port, count):
        super().__init__(daemon=True)
        self.port, self.count, self.closed_by_server, self.stop = port, count, 0, threading.Event()
        self.selector = selectors.DefaultSelector()

    def open_one(self):
        s = socket.create_connection(("127.0.0.1", self.port), timeout=CONNECT_TIMEOUT_S)
        s.setblocking(False)
        self.selector.register(s, selectors.EVENT_READ)

    def run(self):
        for _ in range(self.count):
            self.open_one()
        while not self.stop.is_set():
            for key, _ in self.selector.select(timeout=0.2):
                try:
                    data = key.fileobj.recv(4096)
                except OSError:
                    data = b""
                if not data:  # closed by the server (its request timeout)
                    self.selector.unregister(key.fileobj)
                    key.fileobj.close()
                    self.closed_by_server += 1
                    if not self.stop.is_set():
                        self.open_one()
        for key in list(self.selector.get_map().values()):
            key.fileobj.close()


def status_probe(port):
    """/api/status's answer time in ms, or None when it got none within 5 s."""
    start = time.monotonic()
    try:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=CONNECT_TIMEOUT_S)
        conn.request("GET", "/api/status")
        reply = conn.getresponse()
        reply.read()
        conn.close()
        return (time.monotonic() - start) * 1000 if reply.status == 200 else None
    except OSError:
        return None


def measure(name, plc, hmi_port, seconds, extra=None):
    start = time.monotonic()
    probes = []
    while time.monotonic() < start + seconds:
        probes.append(status_probe(hmi_port))
        time.sleep(max(0.0, 1.0 - (probes[-1] or 0) / 1000))
    end = time.monotonic()
    got = plc.between(start, end)
    cycles = sorted(r[2] for r in got)
    seqs = [r[1] for r in got]
    gaps = sum(1 for a, b in zip(seqs, seqs[1:]) if b != a + 1)
    answered = [p for p in probes if p is not None]
    row = {"phase": name, "seconds": round(end - start, 1), "results": len(got),
           "per_s": round(len(got) / (end - start), 2), "gaps": gaps,
           "cycle_mean_ms": round(statistics.fmean(cycles), 1) if cycles else None,
           "cycle_p95_ms": round(cycles[int(0.95 * (len(cycles) - 1))], 1) if cycles else None,
           "cycle_max_ms": round(cycles[-1], 1) if cycles else None,
           "status_answered": f"{len(answered)}/{len(probes)}",
           "status_ms_max": round(max(answered), 1) if answered else None}
    row.update(extra or {})
    return row


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cellsight", required=True)
    parser.add_argument("--cell", required=True, help="scripts/sim_cell.sh's WORK/cell")
    parser.add_argument("--seconds", type=float, default=30.0, help="length of each phase")
    parser.add_argument("--idle", type=int, default=50, help="idle connections")
    parser.add_argument("--streams", type=int, default=50, help="live streams asked for")
    args = parser.parse_args()

    work = tempfile.mkdtemp(prefix="cellsight-idle-")
    port, hmi_port = free_port(), free_port()
    log = open(os.path.join(work, "cell.log"), "w", encoding="utf-8")
    cell = subprocess.Popen(
        [args.cellsight, "--config", os.path.join(args.cell, "cellsight.yaml"), "run", "--sim", "--wait-plc",
         "--models", os.path.join(args.cell, "models"), "--calibration", os.path.join(args.cell, "calibration.yaml"),
         "--port", str(port), "--hmi-port", str(hmi_port), "--sim-parts", SIM_PARTS, "--seed", "50"],
        stdout=log, stderr=subprocess.STDOUT)
    plc = None
    try:
        wait_port(port, cell)
        wait_port(hmi_port, cell)
        plc = Plc(port)
        time.sleep(3.0)  # the first parts (start-up, caches) are not the steady state
        rows = [measure("quiet", plc, hmi_port, args.seconds)]

        streams = [Stream(hmi_port) for _ in range(args.streams)]
        for s in streams:
            s.start()
        time.sleep(1.0)
        rows.append(measure(f"{args.streams} live views", plc, hmi_port, args.seconds))
        idle = IdleClients(hmi_port, args.idle)
        idle.start()
        time.sleep(1.0)
        rows.append(measure(f"+ {args.idle} idle conns", plc, hmi_port, args.seconds))
        idle.stop.set()
        idle.join()
        served = sum(1 for s in streams if s.status == 200)
        refused = sum(1 for s in streams if s.status == 503)
        for row in rows[1:]:
            row["streams"] = (f"{served} / {refused} / {args.streams - served - refused}, "
                              f"{sum(s.results for s in streams)}")
        rows[2]["idle_closed"] = idle.closed_by_server
        for s in streams:
            s.close()
        time.sleep(1.0)
        rows.append(measure("after", plc, hmi_port, args.seconds))
    finally:
        if plc is not None:
            plc.process.send_signal(signal.SIGTERM)
        cell.send_signal(signal.SIGTERM)
        cell.wait(timeout=30)
        if plc is not None:
            plc.process.wait(timeout=10)
        log.close()

    all_seqs = [r[1] for r in plc.results]
    total_gaps = sum(1 for a, b in zip(all_seqs, all_seqs[1:]) if b != a + 1)
    final = [line for line in open(os.path.join(work, "cell.log"), encoding="utf-8") if "max cycle" in line]
    print("| phase | s | PLC results | per s | gaps | cycle mean / p95 / max ms | /api/status answered, max ms |"
          " live views 200 / 503 / other, results streamed | idle conns closed by the server |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['phase']} | {r['seconds']} | {r['results']} | {r['per_s']} | {r['gaps']} | "
              f"{r['cycle_mean_ms']} / {r['cycle_p95_ms']} / {r['cycle_max_ms']} | "
              f"{r['status_answered']}, {r['status_ms_max']} | {r.get('streams', '–')} | {r.get('idle_closed', '–')} |")
    print(f"PLC: {len(plc.results)} results in all, {total_gaps} gaps, errors: {plc.errors or 'none'}; "
          f"cell exit {cell.returncode}")
    if final:
        print(f"cell: {final[-1].strip()}")
    print(json.dumps(rows))
    print(f"(logs in {work})")
    return 0 if total_gaps == 0 and not plc.errors and cell.returncode == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
