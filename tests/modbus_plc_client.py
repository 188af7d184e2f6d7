#!/usr/bin/env python3
"""A PLC program in Python (pymodbus 3.0) against cellsight's Modbus server: polls, checks, acknowledges results.

Used by tests/test_modbus.cpp as an independent client (its own framing and its own high-word-first decoding via
pymodbus's BinaryPayloadDecoder) and by scripts/demo.sh. Written for register map version 2: it reads the whole
result block 200-234 in one request and accepts it only when both sequence copies equal RESULT_SEQ. Prints one JSON
object per line on stdout:
  {"event": "connected", "map_version": v}
  {"event": "result", "seq": n, "acq_id": n, "code": n, "part_id": n, "confidence": n, "source": n,
   "x_um": n, "y_um": n, "z_um": n, "rx_mdeg": n, "ry_mdeg": n, "rz_mdeg": n, "timestamp_us": n, "cycle_ms": n,
   "sigma_x_um": n, "sigma_y_um": n, "sigma_z_um": n, "sigma_rx_mdeg": n, "sigma_ry_mdeg": n, "sigma_rz_mdeg": n,
   "status": n, "heartbeat": n}
      a pose value that is not available (0x80000000) and a sigma that is not available (0xFFFF) are null
  {"event": "error", "what": "..."}            (a protocol violation seen by the PLC)
  {"event": "done", "results": n, "torn": n, "errors": n, "heartbeat_first": n, "heartbeat_last": n}
Exit status: 0 when --count results arrived in sequence without errors, 1 otherwise (also when MAP_VERSION is not
2: the program was written for another map), 2 when it cannot connect.

Modes: --mode ack (default) does the full handshake of DESIGN.md; --mode poll ignores the ack and reacts to
RESULT_SEQ changing. --input reads the read-only blocks with FC04 instead of FC03.
"""

import argparse
import json
import sys
import time

from pymodbus.client import ModbusTcpClient
from pymodbus.constants import Endian
from pymodbus.payload import BinaryPayloadDecoder

# Register map (drivers/modbus/register_map.hpp); kept literal here on purpose: this is the PLC's view.
CONTROL = 0
PLC_HEARTBEAT = 4
STATUS = 100
STATUS_COUNT = 11
RESULT = 200
RESULT_COUNT = 35  # 200-234: map version 2, well under the 125 registers of one read
TRIGGER_ENABLE = 1 << 0
RESULT_ACK = 1 << 2
RESULT_VALID = 1 << 4
MAP_VERSION_INDEX = 10  # 110 - 100
MAP_VERSION = 2
INVALID_S32 = -0x80000000
INVALID_SIGMA = 0xFFFF
POSE = ("x_um", "y_um", "z_um", "rx_mdeg", "ry_mdeg", "rz_mdeg")
SIGMA = ("sigma_x_um", "sigma_y_um", "sigma_z_um", "sigma_rx_mdeg", "sigma_ry_mdeg", "sigma_rz_mdeg")


def emit(**fields):
    print(json.dumps(fields), flush=True)


class Plc:
    def __init__(self, args):
        self.args = args
        self.client = ModbusTcpClient(args.host, port=args.port, timeout=args.request_timeout, retries=0)
        self.plc_heartbeat = 0
        self.errors = 0

    def check(self, response, what):
        if response is None or response.isError():
            raise RuntimeError(f"{what} failed: {response}")
        return response

    def read(self, address, count):
        if self.args.input:
            rr = self.client.read_input_registers(address, count, slave=self.args.unit)
        else:
            rr = self.client.read_holding_registers(address, count, slave=self.args.unit)
        return self.check(rr, f"read {address}+{count}").registers

    def write(self, address, value):
        self.check(self.client.write_register(address, value, slave=self.args.unit), f"write {address}")

    def beat(self):
        if self.args.heartbeat:
            self.plc_heartbeat = (self.plc_heartbeat + 1) & 0xFFFF
            self.write(PLC_HEARTBEAT, self.plc_heartbeat)

    def error(self, what):
        self.errors += 1
        emit(event="error", what=what)


def decode_block(registers):
    # One FC03 of 35 registers; 32/64-bit values are high word first, big-endian bytes (README "Conventions").
    d = BinaryPayloadDecoder.fromRegisters(registers, byteorder=Endian.Big, wordorder=Endian.Big)
    block = {}
    block["seq"] = d.decode_32bit_uint()
    block["acq_id"] = d.decode_32bit_uint()
    block["code"] = d.decode_16bit_uint()
    block["part_id"] = d.decode_16bit_uint()
    block["confidence"] = d.decode_16bit_uint()
    block["source"] = d.decode_16bit_uint()
    for name in POSE:
        value = d.decode_32bit_int()
        block[name] = None if value == INVALID_S32 else value
    block["timestamp_us"] = d.decode_64bit_uint()
    block["cycle_ms"] = d.decode_16bit_uint()
    block["seq_copy"] = d.decode_32bit_uint()
    for name in SIGMA:
        value = d.decode_16bit_uint()
        block[name] = None if value == INVALID_SIGMA else value
    block["seq_copy2"] = d.decode_32bit_uint()
    return block


def next_seq(seq):
    return 1 if seq == 0xFFFFFFFF else seq + 1  # 0 means "no result yet" and is skipped on wrap


def run(args):
    plc = Plc(args)
    if not plc.client.connect():
        emit(event="error", what=f"cannot connect to {args.host}:{args.port}")
        return 2
    status_regs = plc.read(STATUS, STATUS_COUNT)
    emit(event="connected", map_version=status_regs[MAP_VERSION_INDEX])
    if status_regs[MAP_VERSION_INDEX] != MAP_VERSION:
        plc.error(f"MAP_VERSION is {status_regs[MAP_VERSION_INDEX]}, this program is written for {MAP_VERSION}")
        plc.client.close()
        return 1
    plc.write(CONTROL, TRIGGER_ENABLE)

    deadline = time.monotonic() + args.timeout
    last_seq = None
    got = 0
    torn = 0
    heartbeat_first = status_regs[1]
    heartbeat_last = heartbeat_first
    while got < args.count:
        if time.monotonic() > deadline:
            plc.error(f"timeout after {got} of {args.count} results")
            break
        plc.beat()
        status_regs = plc.read(STATUS, STATUS_COUNT)
        status = status_regs[0]
        heartbeat_last = status_regs[1]
        if not status & RESULT_VALID:
            time.sleep(args.period)
            continue
        block = decode_block(plc.read(RESULT, RESULT_COUNT))
        if block["seq"] != block["seq_copy"] or block["seq"] != block["seq_copy2"]:
            torn += 1  # a real PLC re-reads; the server must never produce one, the C++ test checks torn == 0
            continue
        if block["seq"] == last_seq:
            if args.mode == "poll":
                time.sleep(args.period)
                continue
            plc.error(f"result {block['seq']} still valid after its ack cycle")
            continue
        if last_seq is not None and block["seq"] != next_seq(last_seq):
            plc.error(f"sequence jumped from {last_seq} to {block['seq']}")
        last_seq = block["seq"]
        got += 1
        del block["seq_copy"], block["seq_copy2"]
        emit(event="result", status=status, heartbeat=heartbeat_last, **block)
        if args.mode == "ack":
            plc.write(CONTROL, TRIGGER_ENABLE | RESULT_ACK)
            while True:  # the server drops RESULT_VALID once it has seen the ack
                if time.monotonic() > deadline:
                    plc.error("RESULT_VALID not cleared after RESULT_ACK")
                    break
                plc.beat()
                if not plc.read(STATUS, 1)[0] & RESULT_VALID:
                    break
                time.sleep(args.period)
            plc.write(CONTROL, TRIGGER_ENABLE)  # clearing the ack lets the next queued result appear
    emit(event="done", results=got, torn=torn, errors=plc.errors, heartbeat_first=heartbeat_first,
         heartbeat_last=heartbeat_last)
    plc.client.close()
    return 0 if got == args.count and plc.errors == 0 else 1


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=502)
    parser.add_argument("--unit", type=int, default=1)
    parser.add_argument("--count", type=int, default=1, help="results to collect before exiting")
    parser.add_argument("--mode", choices=("ack", "poll"), default="ack")
    parser.add_argument("--input", action="store_true", help="read status and result blocks with FC04")
    parser.add_argument("--no-heartbeat", dest="heartbeat", action="store_false", help="do not write PLC_HEARTBEAT")
    parser.add_argument("--timeout", type=float, default=20.0, help="seconds for the whole run")
    parser.add_argument("--period", type=float, default=0.002, help="seconds between polls")
    parser.add_argument("--request-timeout", type=float, default=2.0)
    args = parser.parse_args()
    try:
        return run(args)
    except Exception as error:  # noqa: BLE001 - report anything as a JSON line for the C++ test
        emit(event="error", what=f"{type(error).__name__}: {error}")
        return 1


if __name__ == "__main__":
    sys.exit(main())
