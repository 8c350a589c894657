"""Commission the drives ``hil run`` serves over CAN with python ``canopen``'s CiA 402 master,
in a process of its own, as a CANopen user would: the README and docs/canopen.md run this.

::

    python3 examples/canopen_master.py --group 239.74.163.2 --eds eds --nodes 5,6 --out out/master

Steps, each printed as it completes (exit 1 and the reason on the first that fails):

1. **Boot-up**: NMT reset communication to every node; each answers with its boot-up
   message (700h + node-ID, 00h).
2. **EDS**: each node's object dictionary imported from ``hil eds``'s ``nodeN.eds``
   (``BaseNode402(node, "eds/nodeN.eds")``); the identity 1018h read back against it.
3. **PDO mapping** by SDO, in PRE-OPERATIONAL, the CiA 301 way (canopen's
   ``PdoMap.save``: make not valid, count 0, entries, count, valid): RPDO1 = controlword
   6040h (event-driven), RPDO2 = target position 607Ah + velocity offset 60B1h (the speed
   feed-forward; synchronous), TPDO1 = statusword 6041h + following error 60F4h, TPDO2 =
   position actual 6064h (synchronous), the rest off (a valid PDO takes its frame in every
   cycle).  Two nodes then need 905 bits of a 1 ms cycle at 1 Mbit/s (the default mapping
   would need 1635, more than the bus carries: the drives would start with EMCY FF20h
   and lose frames, EMCY 8110h).  Then NMT start.
4. **Homing** (6098h method 5: the home switch and the encoder's index mark above its
   edge; 6099h speeds, 609Ah acceleration), every node at once.
5. **Profile position**: 607Ah, 6081h, 6083h, 6084h by SDO; the new set-point (controlword
   bit 4) acknowledged (statusword bit 12), then target reached (bit 10).
6. **CSP at 1 kHz SYNC on every node**: a smooth move (cosine ramp of ``--csp-mm`` over
   ``--csp-s``) sent as 607Ah targets with their speed as 60B1h, one per SYNC: each cycle the RPDO2 of every node,
   then SYNC with its counter, from this loop; 60F4h comes back by TPDO1 with the SYNC it
   answers (the drive's echo of the counter), 6064h by TPDO2, into ``OUT/csp.csv`` (one
   row per node and SYNC answered, with the time the SYNC went out).
7. **Heartbeat loss**: the drives consume this master's heartbeat (1016h, 500 ms); it
   stops, each drive faults (EMCY 8130h, FAULT), the heartbeat comes back, a fault reset
   brings each to OPERATION ENABLED again.

``OUT/summary.json`` has each step's result.  A master producing SYNC wants a steady
cycle: ``--realtime`` runs this one at SCHED_FIFO on a CPU of its own (as root).

**The one setting over udp_multicast**: every process on python-can's ``udp_multicast``
bus receives its own frames too.  canopen takes the copy of an RPDO it sent for a PDO
that is being sent periodically by someone else, and from then on no longer sends the
controlword when it changes.  So this master *starts its RPDO1 periodically*
(``node.rpdo[1].start(SYNC_S)``), as a master producing SYNC sends its process data every
cycle anyway: canopen ignores the copies of a PDO it is sending itself.  The RPDO2 of the
CSP loop is sent explicitly, before each SYNC, and never read back.
"""

import argparse
import csv
import json
import math
import os
import sys
import time
from pathlib import Path

import canopen
from canopen.profiles.p402 import BaseNode402

SYNC_S = 0.001                 # the communication cycle period (1006h's default)
MASTER_ID = 127                # this master's heartbeat: 77Fh
HEARTBEAT_S = 0.05
#: 1016h: the drives' consumer heartbeat time, ms: ten of the master's heartbeats (a
#: Python thread on a loaded machine can be held up for over 100 ms)
CONSUMER_MS = 500
HOMING_METHOD = 5
TIMEOUT_S = 10.0               # bound on every wait
CW_ENABLE, CW_NEW_SET_POINT, CW_FAULT_RESET = 0x000F, 0x0010, 0x0080
#: the SYNC counter (CiA 301: 1-240) and the drive's echo of it in a statusword sent at
#: such a SYNC: bit 8 set, the counter's low two bits in bits 14-15
SYNC_COUNTER_MAX = 240
SW_ECHO, ECHO_SHIFT = 1 << 8, 14
SW_TARGET_REACHED, SW_ACK, SW_HOMING_ERROR = 1 << 10, 1 << 12, 1 << 13


class StepFailed(RuntimeError):
    pass


def wait(predicate, what: str, limit_s: float = TIMEOUT_S) -> None:
    end = time.monotonic() + limit_s
    while not predicate():
        if time.monotonic() > end:
            raise StepFailed(f"gave up waiting for {what}")
        time.sleep(0.002)


class Master:
    def __init__(self, args):
        self.args = args
        self.network = canopen.Network()
        self.network.connect(interface="udp_multicast", channel=args.group, port=args.port)
        self.nodes: dict[int, BaseNode402] = {}
        self.heartbeat = None
        self.summary: dict = {"steps": []}

    def step(self, name: str, result) -> None:
        self.summary["steps"].append(name)
        self.summary[name] = result
        print(f"{name}: {result}", flush=True)

    # 1, 2
    def boot(self) -> None:
        for n in self.args.nodes:
            node = BaseNode402(n, str(Path(self.args.eds) / f"node{n}.eds"))
            node.sdo.RESPONSE_TIMEOUT = 2.0
            for name in ("TIMEOUT_SWITCH_OP_MODE", "TIMEOUT_SWITCH_STATE_FINAL",
                         "TIMEOUT_SWITCH_STATE_SINGLE", "TIMEOUT_CHECK_TPDO"):
                setattr(node, name, 2.0)  # a loaded machine: generous, still bounded
            self.network.add_node(node)
            self.nodes[n] = node
        booted = set()
        for n, node in self.nodes.items():  # listening before the reset: no boot-up missed
            node.nmt.add_heartbeat_callback(lambda state, n=n: state == 0 and booted.add(n))
            node.nmt.state = "RESET COMMUNICATION"
        wait(lambda: booted == set(self.nodes), "the boot-up of every node")
        self.step("boot-up", sorted(booted))
        identity = {}
        for n, node in self.nodes.items():
            declared = node.object_dictionary[0x1018][1].default
            got = node.sdo[0x1018][1].raw
            if got != declared:
                raise StepFailed(f"node {n}: vendor {got:#x}, the EDS says {declared:#x}")
            identity[n] = {"vendor": f"{got:#010x}", "product": node.sdo[0x1018][2].raw,
                           "modes_6502h": f"{node.sdo[0x6502].raw:#x}"}
        self.step("eds", identity)

    # 3
    def remap(self) -> None:
        for node in self.nodes.values():
            node.rpdo.read()
            node.tpdo.read()
            for pdos, layout in ((node.rpdo, {1: ((0x6040,), 255),
                                              2: ((0x607A, 0x60B1), 1)}),
                                 (node.tpdo, {1: ((0x6041, 0x60F4), 1), 2: ((0x6064,), 1)})):
                for k in (1, 2, 3, 4):
                    pdo = pdos[k]
                    pdo.clear()
                    pdo.enabled = k in layout
                    if pdo.enabled:
                        objects, pdo.trans_type = layout[k]
                        for index in objects:
                            pdo.add_variable(index)
                pdos.save()
            node.setup_402_state_machine(read_pdos=False)
            node.rpdo[1][0x6040].raw = 0
            node.rpdo[1].start(SYNC_S)  # the one setting (see the module docstring)
        for node in self.nodes.values():
            node.sdo[0x1016][1].raw = MASTER_ID << 16 | CONSUMER_MS
            node.nmt.state = "OPERATIONAL"
        self.heartbeat = self.network.send_periodic(0x700 + MASTER_ID, [0x05], HEARTBEAT_S)
        self.network.sync.start(SYNC_S)
        for n, node in self.nodes.items():
            if node.tpdo[1].wait_for_reception(TIMEOUT_S) is None:
                raise StepFailed(f"node {n} did not start (EMCY: {node.emcy.log})")
        self.step("pdo mapping", {n: [f"{v.index:04X}h" for k in (1, 2) for v in node.tpdo[k]]
                                  for n, node in self.nodes.items()})

    def enable(self, mode: str) -> None:
        for n, node in self.nodes.items():
            node.op_mode = mode
            if node.op_mode != mode:
                raise StepFailed(f"node {n} did not take {mode}")
            node.state = "OPERATION ENABLED"

    def statusword(self, node: BaseNode402) -> int:
        node.tpdo[1].wait_for_reception(TIMEOUT_S)
        return node.tpdo[1][0x6041].raw

    # 4
    def home(self) -> None:
        a = self.args
        for node in self.nodes.values():
            node.sdo[0x6098].raw = HOMING_METHOD
            node.sdo[0x6099][1].raw = round(a.homing_speed_switch)
            node.sdo[0x6099][2].raw = round(a.homing_speed_zero)
            node.sdo[0x609A].raw = round(a.homing_acceleration)
            node.sdo[0x607C].raw = 0
        self.enable("HOMING")
        for node in self.nodes.values():
            node.controlword = CW_ENABLE | CW_NEW_SET_POINT
        homed = {}
        for n, node in self.nodes.items():
            # bits 13, 12, 10: 0 0 1 is "not started" (the start is a cycle or two on its
            # way), 0 1 1 attained, 1 x x an error
            wait(lambda node=node: self.statusword(node) & 0x3400 != 0x0400,
                 f"homing started on node {n}")
            wait(lambda node=node: self.statusword(node) & 0x3400 in (0x1400, 0x2000, 0x2400),
                 f"node {n} homed", 60.0)
            if self.statusword(node) & SW_HOMING_ERROR:
                raise StepFailed(f"node {n}: homing error (EMCY: {node.emcy.log})")
            homed[n] = node.sdo[0x6064].raw
        for node in self.nodes.values():
            node.controlword = CW_ENABLE
        self.step("homing", homed)

    # 5
    def profile_position(self) -> None:
        a = self.args
        self.enable("PROFILED POSITION")
        for node in self.nodes.values():
            node.sdo[0x6081].raw = round(a.pp_speed)
            node.sdo[0x6083].raw = node.sdo[0x6084].raw = round(a.pp_acceleration)
            node.sdo[0x607A].raw = round(a.pp_target)
            node.controlword = CW_ENABLE | CW_NEW_SET_POINT
        for n, node in self.nodes.items():
            wait(lambda node=node: self.statusword(node) & SW_ACK, f"set-point ack of {n}")
            node.controlword = CW_ENABLE
        reached = {}
        for n, node in self.nodes.items():
            wait(lambda node=node: not self.statusword(node) & SW_ACK
                 and self.statusword(node) & SW_TARGET_REACHED, f"target of node {n}", 30.0)
            reached[n] = node.sdo[0x6064].raw
        self.step("profile position", reached)

    # 6
    def csp(self) -> None:
        a = self.args
        starts = {}
        for n, node in self.nodes.items():
            starts[n] = node.sdo[0x6064].raw
            node.rpdo[2][0x607A].raw, node.rpdo[2][0x60B1].raw = starts[n], 0
            node.rpdo[2].transmit()
        self.enable("CYCLIC SYNCHRONOUS POSITION")
        rows, synced = [], [0]

        def taken(pdo, n):
            """canopen's receive thread: TPDO1 of node n.  The drive echoes the SYNC
            counter's low two bits in statusword bits 14-15 (bit 8 set): the answer to the
            last SYNC sent with them, even when it is read after the next went out."""
            sw, last = pdo[0x6041].raw, synced[0]
            # SYNC k carries the counter k % 240 + 1, whose low two bits are k + 1's
            k = last - ((last + 1 - (sw >> ECHO_SHIFT)) & 3) if sw & SW_ECHO else last
            rows.append((k, n, self.nodes[n].tpdo[2][0x6064].raw, pdo[0x60F4].raw))

        callbacks = {n: (lambda pdo, n=n: taken(pdo, n)) for n in self.nodes}
        for n, node in self.nodes.items():
            node.tpdo[1].add_callback(callbacks[n])
        distance = a.csp_mm * a.counts_per_mm
        cycles = round(a.csp_s / SYNC_S)
        settle = round(0.5 / SYNC_S)
        targets, feedforward, sent = {}, {}, {}
        self.network.sync.stop()
        start = deadline = time.monotonic()
        for k in range(1, cycles + settle + 1):
            share = 0.5 * (1 - math.cos(math.pi * min(k, cycles) / cycles))
            for i, (n, node) in enumerate(self.nodes.items()):
                target = round(starts[n] + (-1) ** i * distance * share)
                # the speed over the cycle the drive interpolates this target in (60C2h)
                speed = round((target - targets.get((k - 1, n), starts[n])) / SYNC_S)
                targets[(k, n)], feedforward[(k, n)] = target, speed
                node.rpdo[2][0x607A].raw, node.rpdo[2][0x60B1].raw = target, speed
                node.rpdo[2].transmit()
            self.network.sync.transmit(k % SYNC_COUNTER_MAX + 1)
            now = time.monotonic()
            sent[k] = now - start
            synced[0] = k
            deadline = max(deadline + SYNC_S, now)  # held up: go on from now, no burst
            time.sleep(max(0.0, deadline - time.monotonic()))
        self.network.sync.start(SYNC_S)
        for n, node in self.nodes.items():  # BaseNode402's own callback stays
            node.tpdo[1].callbacks.remove(callbacks[n])
        out = Path(a.out)
        with open(out / "csp.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["sync", "sent_s", "node", "target", "velocity_offset", "position",
                        "following_error"])
            for k, n, position, fe in rows:
                if (k, n) in targets:
                    w.writerow([k, f"{sent[k]:.6f}", n, targets[(k, n)],
                                feedforward[(k, n)], position, fe])
        worst = {n: max(abs(fe) for _, m, _, fe in rows if m == n) for n in self.nodes}
        self.step("csp", {"syncs": cycles + settle, "rows": len(rows),
                          "max_following_error": worst})

    # 7
    def lose_heartbeat(self) -> None:
        self.heartbeat.stop()
        for n, node in self.nodes.items():
            wait(lambda node=node: any(e.code == 0x8130 for e in node.emcy.log),
                 f"EMCY 8130h from node {n}")
            wait(lambda node=node: node.state == "FAULT", f"FAULT of node {n}")
        codes = {n: node.sdo[0x603F].raw for n, node in self.nodes.items()}
        self.heartbeat = self.network.send_periodic(0x700 + MASTER_ID, [0x05], HEARTBEAT_S)
        for n, node in self.nodes.items():
            node.controlword = 0
            node.check_statusword()
            node.controlword = CW_FAULT_RESET
            wait(lambda node=node: node.state != "FAULT", f"fault reset of node {n}")
            node.state = "OPERATION ENABLED"
            if node.sdo[0x603F].raw != 0:
                raise StepFailed(f"node {n} still has 603Fh = {node.sdo[0x603F].raw:#x}")
        self.step("heartbeat loss", {n: f"{c:#06x}" for n, c in codes.items()})

    def close(self) -> None:
        for node in self.nodes.values():
            try:
                node.state = "SWITCH ON DISABLED"
            except RuntimeError:
                pass
            node.rpdo[1].stop()
        if self.heartbeat is not None:
            self.heartbeat.stop()
        self.network.sync.stop()
        self.network.disconnect()


def parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--group", default="239.74.163.2", help="udp_multicast group (routed "
                   "over lo: ip route add GROUP/32 dev lo)")
    p.add_argument("--port", type=int, default=43113)
    p.add_argument("--nodes", default="5", type=lambda s: [int(n) for n in s.split(",")])
    p.add_argument("--eds", default="eds", help="folder of hil eds's nodeN.eds")
    p.add_argument("--out", default="master", help="folder for csp.csv and summary.json")
    # increments of the Arrow 500 X (4194304 per revolution of a 10 mm lead)
    p.add_argument("--counts-per-mm", type=float, default=419430.4)
    p.add_argument("--homing-speed-switch", type=float, default=20 * 419430.4,
                   help="6099h:01, increments/s (default 20 mm/s)")
    p.add_argument("--homing-speed-zero", type=float, default=5 * 419430.4,
                   help="6099h:02, increments/s (default 5 mm/s)")
    p.add_argument("--homing-acceleration", type=float, default=500 * 419430.4,
                   help="609Ah, increments/s² (default 0.5 m/s²)")
    p.add_argument("--pp-target", type=float, default=30 * 419430.4,
                   help="607Ah after homing, increments (default 30 mm)")
    p.add_argument("--pp-speed", type=float, default=50 * 419430.4, help="6081h")
    p.add_argument("--pp-acceleration", type=float, default=500 * 419430.4,
                   help="6083h = 6084h")
    p.add_argument("--csp-mm", type=float, default=20.0,
                   help="CSP move, mm (node 2 moves the other way)")
    p.add_argument("--csp-s", type=float, default=1.0, help="CSP move duration, s")
    p.add_argument("--realtime", action="store_true", help="SCHED_FIFO 50, pinned to --cpu "
                   "(hil run takes the last CPU)")
    p.add_argument("--cpu", type=int, default=0, help="the CPU for --realtime (default 0)")
    return p.parse_args(argv)


def realtime(cpu: int) -> None:
    """SCHED_FIFO priority 50 on ``cpu`` for this process and the threads it starts after
    (canopen's receive thread, python-can's periodic senders): a steady SYNC.  Where it is
    not permitted, a note and on as it is."""
    try:
        os.sched_setaffinity(0, {cpu})
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
    except OSError as e:
        print(f"canopen_master: no real-time scheduling ({e}); the SYNC will jitter",
              file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    if args.realtime:
        realtime(args.cpu)
    master = Master(args)
    status = 0
    try:
        master.boot()
        master.remap()
        master.home()
        master.profile_position()
        master.csp()
        master.lose_heartbeat()
    except (StepFailed, canopen.SdoAbortedError, canopen.SdoCommunicationError,
            canopen.nmt.NmtError) as e:
        print(f"canopen_master: {e}", file=sys.stderr, flush=True)
        master.summary["error"] = str(e)
        status = 1
    finally:
        master.close()
        (Path(args.out) / "summary.json").write_text(json.dumps(master.summary, indent=1))
    return status


if __name__ == "__main__":
    sys.exit(main())
