#!/usr/bin/env python3
"""Figures of the DICOM receiver's network side against a real decima-server (server/README.md,
"PACS side"). Starts the server on loopback ports in a temp folder, then measures:
  - a storescu send of a series alone, and beside ten silent TCP connections (from 127.0.0.2)
    and one accepted association that stays silent (from 127.0.0.3), --repeat sends each;
  - the server's peak RSS (VmHWM) before and after storescu sends a deflate bomb (a few hundred
    KiB that inflate to --bomb-mib of zeros) under --max-upload-mb 64;
  - echoscu's answer.
Prints one JSON object. Usage:
  tests/e2e/dicom_scp_figures.py build/server/decima-server ../shared/data/ct-head-256x256x113-dicom
"""
import argparse
import glob
import json
import os
import shutil
import signal
import socket
import statistics
import struct
import subprocess
import tempfile
import time
import zlib


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def vm(pid, key):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) // 1024
    return -1


def associate_rq(called, calling):
    def item(t, body):
        return struct.pack(">BBH", t, 0, len(body)) + body
    pc = item(0x20, b"\x01\0\0\0" + item(0x30, b"1.2.840.10008.1.1") + item(0x40, b"1.2.840.10008.1.2"))
    user = item(0x50, item(0x51, struct.pack(">I", 16384)))
    body = (b"\0\x01\0\0" + called.ljust(16).encode() + calling.ljust(16).encode() + b"\0" * 32
            + item(0x10, b"1.2.840.10008.3.1.1.1") + pc + user)
    return struct.pack(">BBI", 1, 0, len(body)) + body


def deflate_bomb(path, mib):
    def el(g, e, vr, v):
        if len(v) % 2:
            v += b"\0" if vr == "UI" else b" "
        return struct.pack("<HH", g, e) + vr.encode() + struct.pack("<H", len(v)) + v
    sop_class, sop = b"1.2.840.10008.5.1.4.1.1.2", b"1.2.826.0.1.3680043.9.7777.42.1"
    meta = (struct.pack("<HH", 2, 1) + b"OB\0\0" + struct.pack("<I", 2) + b"\0\x01"
            + el(2, 2, "UI", sop_class) + el(2, 3, "UI", sop)
            + el(2, 0x10, "UI", b"1.2.840.10008.1.2.1.99"))
    head = (el(8, 0x16, "UI", sop_class) + el(8, 0x18, "UI", sop)
            + el(0x20, 0xE, "UI", b"1.2.826.0.1.3680043.9.7777.42")
            + el(0x29, 0x10, "LO", b"BOMB") + struct.pack("<HH", 0x29, 0x1001) + b"OB\0\0"
            + struct.pack("<I", mib << 20))
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    zeros = b"\0" * (1 << 20)
    with open(path, "wb") as f:
        f.write(b"\0" * 128 + b"DICM" + struct.pack("<HH", 2, 0) + b"UL" + struct.pack("<HI", 4, len(meta))
                + meta + c.compress(head))
        for _ in range(mib):
            f.write(c.compress(zeros))
        f.write(c.flush())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("server")
    ap.add_argument("series", help="folder of .dcm files to send")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--bomb-mib", type=int, default=512)
    a = ap.parse_args()
    work = tempfile.mkdtemp(prefix="decima-scp-figures-")
    port = free_port()
    log = open(os.path.join(work, "server.log"), "w")
    srv = subprocess.Popen([a.server, "--listen", "127.0.0.1:0", "--data-dir", os.path.join(work, "d"),
                            "--dicom-listen", f"127.0.0.1:{port}", "--dicom-min-free-mb", "0",
                            "--dicom-quiet-seconds", "3600", "--max-upload-mb", "64"],
                           stdout=log, stderr=log)
    env = dict(os.environ, TCP_NODELAY="1")
    files = sorted(glob.glob(os.path.join(a.series, "*.dcm")))
    out = {"instances": len(files)}
    held = []
    try:
        for _ in range(100):
            if "listening on 127.0.0.1:%d" % port in open(os.path.join(work, "server.log")).read():
                break
            time.sleep(0.1)
        scu = lambda *args: subprocess.run(["storescu", "-aec", "DECIMA", "127.0.0.1", str(port), *args],
                                           env=env, capture_output=True, timeout=300)
        out["echoscu_rc"] = subprocess.run(["echoscu", "-aec", "DECIMA", "127.0.0.1", str(port)],
                                           capture_output=True, timeout=60).returncode
        idle_rss = vm(srv.pid, "VmRSS")

        def timed():
            t0 = time.monotonic()
            rc = scu(*files).returncode
            assert rc == 0, rc
            return time.monotonic() - t0
        alone = [timed() for _ in range(a.repeat)]
        # From another address than the sender's, as an idle device on the network would be
        # (one address may hold at most --dicom-max-per-peer, default 8, connections).
        for _ in range(10):
            held.append(socket.create_connection(("127.0.0.1", port), source_address=("127.0.0.2", 0)))
        s = socket.create_connection(("127.0.0.1", port), source_address=("127.0.0.3", 0))
        s.sendall(associate_rq("DECIMA", "SILENT"))
        out["silent_association_accepted"] = s.recv(1)[:1] == b"\x02"
        held.append(s)
        beside = [timed() for _ in range(a.repeat)]
        out["send_alone_s"] = [round(x, 3) for x in alone]
        out["send_beside_11_silent_s"] = [round(x, 3) for x in beside]
        out["median_delay_s"] = round(statistics.median(beside) - statistics.median(alone), 3)
        for h in held:
            h.close()
        bomb = os.path.join(work, "bomb.dcm")
        deflate_bomb(bomb, a.bomb_mib)
        out["bomb_file_kib"] = os.path.getsize(bomb) // 1024
        out["bomb_inflated_mib"] = a.bomb_mib
        out["server_rss_idle_mib"] = idle_rss
        out["server_hwm_before_bomb_mib"] = vm(srv.pid, "VmHWM")
        t0 = time.monotonic()
        r = scu("--propose-deflated", bomb)
        out["bomb_storescu_rc"] = r.returncode
        out["bomb_refused_after_s"] = round(time.monotonic() - t0, 3)
        out["server_hwm_after_bomb_mib"] = vm(srv.pid, "VmHWM")
        out["server_rss_after_bomb_mib"] = vm(srv.pid, "VmRSS")
    finally:
        for h in held:
            h.close()
        srv.send_signal(signal.SIGTERM)
        try:
            srv.wait(30)
        except subprocess.TimeoutExpired:
            srv.kill()
            srv.wait()
        shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
