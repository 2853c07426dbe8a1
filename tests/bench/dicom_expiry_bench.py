#!/usr/bin/python3
"""The expiry figure of the DICOM receiver (issue 35): N junk series (one small CT slice each,
with its own Study/Series/SOP Instance UIDs, which DCMTK's dump2dcm +Ug makes when the dump has
none) are sent by storescu from one calling AE title to a real decima-server with a short
--dicom-incomplete-expiry, and the data dir is measured (du -sb, and its blobs/ part) before the
send, after it, and once the server expired them without any operator action. Loopback only;
the server is stopped by its PID; every wait is bounded. Not a ctest: a benchmark program that
prints one JSON object.

usage: dicom_expiry_bench.py DECIMA_SERVER_BIN DECIMA_CLI_BIN [--series 1000] [--expiry 5]
"""
import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time

DUMP = """(0008,0016) UI =CTImageStorage
(0008,0060) CS [CT]
(0010,0010) PN [Junk^Series]
(0020,0013) IS [1]
(0020,0032) DS [0\\0\\0]
(0020,0037) DS [1\\0\\0\\0\\1\\0]
(0028,0002) US 1
(0028,0004) CS [MONOCHROME2]
(0028,0010) US 4
(0028,0011) US 3
(0028,0030) DS [1\\1]
(0028,0100) US 16
(0028,0101) US 16
(0028,0102) US 15
(0028,0103) US 0
(7fe0,0010) OW 0001\\0002\\0003\\0004\\0005\\0006\\0007\\0008\\0009\\000a\\000b\\000c
"""


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def du(path):
    out = subprocess.run(["du", "-sb", path], capture_output=True, text=True, check=True)
    return int(out.stdout.split()[0])


def blob_files(data):
    return sum(len(files) for _, _, files in os.walk(os.path.join(data, "blobs", "sha256")))


def receives(cli, server):
    r = subprocess.run([cli, "--server", server, "series", "--all", "-o", "json"],
                       capture_output=True, text=True, timeout=120)
    if r.returncode != 0:
        sys.exit(f"decima series: {r.stderr}")
    return [json.loads(line) for line in r.stdout.splitlines() if line.strip()]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("server_bin")
    ap.add_argument("cli_bin")
    ap.add_argument("--series", type=int, default=1000)
    ap.add_argument("--expiry", type=float, default=5)
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="decima-expiry-bench-")
    junk = os.path.join(tmp, "junk")
    os.makedirs(junk)
    dump = os.path.join(tmp, "slice.dump")
    with open(dump, "w") as f:
        f.write(DUMP)
    for i in range(a.series):
        subprocess.run(["dump2dcm", "+Ug", "+te", dump, os.path.join(junk, f"{i:05d}.dcm")],
                       check=True)
    data = os.path.join(tmp, "data")
    port_file = os.path.join(tmp, "port")
    dicom_port = free_port()
    log = open(os.path.join(tmp, "server.log"), "w")
    server = subprocess.Popen(
        [a.server_bin, "--data-dir", data, "--listen", "127.0.0.1:0", "--port-file", port_file,
         "--dicom-listen", f"127.0.0.1:{dicom_port}", "--dicom-min-free-mb", "0",
         "--dicom-incomplete-expiry", str(a.expiry)], stdout=log, stderr=log)
    try:
        for _ in range(600):
            if os.path.exists(port_file) and open(port_file).read().strip():
                break
            time.sleep(0.05)
        else:
            sys.exit("decima-server wrote no port within 30 s")
        addr = "127.0.0.1:" + open(port_file).read().strip()
        time.sleep(1)  # the receiver's first settle pass and the store's first checkpoint
        before = {"data_dir_bytes": du(data), "blobs_bytes": du(os.path.join(data, "blobs")),
                  "blob_files": blob_files(data)}
        t0 = time.monotonic()
        r = subprocess.run(["storescu", "-aet", "JUNK", "-aec", "DECIMA", "+sd", "127.0.0.1",
                            str(dicom_port), junk], capture_output=True, text=True, timeout=600)
        send_s = time.monotonic() - t0
        if r.returncode != 0:
            sys.exit(f"storescu: {r.stderr[-500:]}")
        after_send = {"data_dir_bytes": du(data), "blobs_bytes": du(os.path.join(data, "blobs")),
                      "blob_files": blob_files(data),
                      "waiting": sum(1 for x in receives(a.cli_bin, addr)
                                     if x.get("state") in ("RECEIVING", "INCOMPLETE"))}
        t1 = time.monotonic()
        states = {}
        for _ in range(int((a.expiry + 120) / 0.5)):
            rows = receives(a.cli_bin, addr)
            states = {}
            for x in rows:
                states[x.get("state")] = states.get(x.get("state"), 0) + 1
            if states.get("EXPIRED", 0) >= a.series and not states.get("RECEIVING") \
                    and not states.get("INCOMPLETE"):
                break
            time.sleep(0.5)
        expired_s = time.monotonic() - t1
        after_expiry = {"data_dir_bytes": du(data), "blobs_bytes": du(os.path.join(data, "blobs")),
                        "blob_files": blob_files(data), "states": states}
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
    print(json.dumps({"series": a.series, "expiry_s": a.expiry, "send_s": round(send_s, 2),
                      "expired_within_s_after_send": round(expired_s, 2), "before": before,
                      "after_send": after_send, "after_expiry": after_expiry, "tmp": tmp}))


if __name__ == "__main__":
    main()
