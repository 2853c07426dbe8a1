"""Fixtures of the decima_client tests: a real decima-server on a loopback port with a scratch
data dir and a bearer token, tiny NIfTI volumes, and the real `decima` CLI to compare messages
with. Every process is started here and stopped by its PID; every wait is bounded.

Environment (set by run_tests.py from CMake): DECIMA_SERVER_BIN, DECIMA_CLI_BIN, and
DECIMA_SHARED_DATA (the folder of the real volumes; tests that need them skip without it).
"""
import hashlib
import os
import signal
import socket
import struct
import subprocess
import time

import pytest

TOKEN = "pytest-token"


def _binary(var):
    path = os.environ.get(var, "")
    if not path or not os.access(path, os.X_OK):
        pytest.skip(f"{var} is not set to an executable (run through ctest or run_tests.py)")
    return path


@pytest.fixture(scope="session")
def server_bin():
    return _binary("DECIMA_SERVER_BIN")


@pytest.fixture(scope="session")
def cli_bin():
    return _binary("DECIMA_CLI_BIN")


def free_port():
    """A port nothing listens on now (bound and released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """decima-server on 127.0.0.1, --token-file with TOKEN, the test fault seam on."""

    def __init__(self, binary, workdir, port=0, extra=()):
        self.binary, self.workdir, self.extra = binary, workdir, list(extra)
        self.data_dir = os.path.join(workdir, "data")
        self.token_file = os.path.join(workdir, "token")
        with open(self.token_file, "w", encoding="utf-8") as f:
            f.write(TOKEN + "\n")
        self.port = port
        self.proc = None
        self.start()

    @property
    def address(self):
        return f"127.0.0.1:{self.port}"

    def start(self):
        port_file = os.path.join(self.workdir, "port")
        if os.path.exists(port_file):
            os.remove(port_file)
        args = [self.binary, "--listen", f"127.0.0.1:{self.port}", "--data-dir", self.data_dir,
                "--port-file", port_file, "--token-file", self.token_file, "--allow-faults",
                "--heartbeat-seconds", "1", "--drain-seconds", "0"] + self.extra
        self.log = open(os.path.join(self.workdir, "server.log"), "ab")
        self.proc = subprocess.Popen(args, stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"decima-server exited with {self.proc.returncode}: "
                                   f"{self.read_log()}")
            try:
                with open(port_file, encoding="utf-8") as f:
                    self.port = int(f.read().strip())
                return
            except (OSError, ValueError):
                time.sleep(0.05)
        self.stop(signal.SIGKILL)
        raise RuntimeError("decima-server did not write its port within 30 s: " + self.read_log())

    def stop(self, sig=signal.SIGTERM):
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self.proc = None
        self.log.close()

    def read_log(self):
        with open(os.path.join(self.workdir, "server.log"), "rb") as f:
            return f.read().decode(errors="replace")[-4000:]


@pytest.fixture(scope="session")
def server(server_bin, tmp_path_factory):
    s = Server(server_bin, str(tmp_path_factory.mktemp("server")))
    yield s
    s.stop()


@pytest.fixture
def client(server):
    import decima_client

    with decima_client.Client(server.address, token=TOKEN, timeout=30, reconnect=30) as c:
        yield c


# Small and quick: a 12x10x8 volume, 64 px pictures.
QUICK = {"regions": 2, "image_size": 64}


def sha256(path):
    with open(path, "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def first_line(text):
    return text.strip().splitlines()[0] if text.strip() else ""


def volume_names(client):
    """The names of every volume on the client's server."""
    from decima_client.proto import volumes_pb2

    resp = client._volumes.ListVolumes(volumes_pb2.ListVolumesRequest(page_size=1000),
                                       timeout=10, metadata=client._metadata())
    return {v.name for v in resp.volumes}


def run_cli(cli_bin, address, args, token=TOKEN, timeout=60):
    """Runs `decima --server ADDRESS ARGS...`; returns (exit code, stdout, stderr)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("DECIMA_")}
    if token:
        env["DECIMA_TOKEN"] = token
    p = subprocess.run([cli_bin, "--server", address] + list(args), capture_output=True,
                       text=True, timeout=timeout, env=env, check=False)
    return p.returncode, p.stdout, p.stderr


def write_tiny_nifti(path, nx=12, ny=10, nz=8, seed=0):
    """A NIfTI-1 int16 volume with 2 mm voxels: a bright sphere (1000) in a darker box (100),
    `seed` in the first voxel so different seeds give different blobs (as the C++ e2e tests'
    WriteTinyNifti)."""
    hdr = bytearray(352)
    struct.pack_into("<i", hdr, 0, 348)
    struct.pack_into("<8h", hdr, 40, 3, nx, ny, nz, 1, 1, 1, 1)
    struct.pack_into("<hh", hdr, 70, 4, 16)  # int16
    struct.pack_into("<4f", hdr, 76, 1.0, 2.0, 2.0, 2.0)  # qfac, mm
    struct.pack_into("<ff", hdr, 108, 352.0, 1.0)  # vox_offset, scl_slope
    hdr[123] = 10  # mm, s
    struct.pack_into("<h", hdr, 252, 1)  # qform_code: scanner
    hdr[344:348] = b"n+1\0"
    cx, cy, cz, r = nx / 2, ny / 2, nz / 2, min(nx, ny, nz) / 3
    voxels = []
    for z in range(nz):
        for y in range(ny):
            for x in range(nx):
                d2 = (x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2
                voxels.append(1000 if d2 < r * r else 100)
    voxels[0] = seed
    with open(path, "wb") as f:
        f.write(bytes(hdr))
        f.write(struct.pack(f"<{len(voxels)}h", *voxels))
    return str(path)


# ctest's SKIP_RETURN_CODE: a run in which every test skipped (no server binary, no shared
# data) exits 77, so ctest reports it SKIPPED rather than passed.
_outcomes = {"passed": 0, "failed": 0, "skipped": 0}


def pytest_runtest_logreport(report):
    if report.when == "call" or report.outcome != "passed":
        _outcomes[report.outcome] = _outcomes.get(report.outcome, 0) + 1


def pytest_sessionfinish(session, exitstatus):
    if exitstatus == 0 and _outcomes["skipped"] and not _outcomes["passed"] \
            and not _outcomes["failed"]:
        session.exitstatus = 77
