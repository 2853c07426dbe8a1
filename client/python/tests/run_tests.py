#!/usr/bin/python3
"""The ctest driver of the decima_client tests, the way a user installs the package: a fresh
venv that sees Debian's python3-grpcio and python3-protobuf (--system-site-packages), then
`pip install` of a copy of client/python (with proto/ beside it, as in a checkout) with every
package index and find-links switched off, so the install is proven to need no network; then
pytest (Debian's python3-pytest) in that venv against the real decima-server.

usage: run_tests.py SERVER_BIN CLI_BIN WORK_DIR SHARED_DATA [--require FILE] [pytest args...]
Exit 77 (ctest: skipped) when python3-grpcio, python3-protobuf, python3-pytest or venv is
missing, when --require names a file that is not in SHARED_DATA (checked before the venv is
made), or when every test skipped; else pytest's exit code. Prints the venv and install times
and, when the CT head ran, its figures as one JSON line.
"""
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import time

SKIP = 77
HERE = os.path.dirname(os.path.abspath(__file__))
PACKAGE = os.path.dirname(HERE)  # client/python
SOURCE = os.path.dirname(os.path.dirname(PACKAGE))  # the checkout


def main():
    if len(sys.argv) < 5:
        sys.exit(__doc__)
    server_bin, cli_bin, work, shared = (os.path.abspath(a) for a in sys.argv[1:5])
    pytest_args = sys.argv[5:]
    if pytest_args[:1] == ["--require"] and len(pytest_args) >= 2:
        required = os.path.join(shared, pytest_args[1])
        if not os.path.isfile(required):
            print(f"SKIPPED: {required} is absent (the shared data beside the checkout)")
            return SKIP
        pytest_args = pytest_args[2:]
    for module, package in (("grpc", "python3-grpcio"), ("google.protobuf", "python3-protobuf"),
                            ("pytest", "python3-pytest"), ("venv", "python3-venv"),
                            ("ensurepip", "python3-venv")):
        if importlib.util.find_spec(module) is None:
            print(f"SKIPPED: {package} is not installed (deploy/install-deps.sh installs it)")
            return SKIP
    shutil.rmtree(work, ignore_errors=True)
    os.makedirs(work)
    # A copy of the package and the protos, so the build leaves nothing in the checkout.
    src = os.path.join(work, "src")
    shutil.copytree(PACKAGE, os.path.join(src, "client", "python"),
                    ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    shutil.copytree(os.path.join(SOURCE, "proto"), os.path.join(src, "proto"))
    venv = os.path.join(work, "venv")
    t0 = time.monotonic()
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", venv], check=True,
                   timeout=300)
    venv_s = time.monotonic() - t0
    python = os.path.join(venv, "bin", "python")
    offline = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")}
    offline.update(PIP_NO_INDEX="1", PIP_CONFIG_FILE=os.devnull,
                   PIP_DISABLE_PIP_VERSION_CHECK="1")
    t0 = time.monotonic()
    install = subprocess.run([python, "-m", "pip", "install", "./client/python"], cwd=src,
                             env=offline, capture_output=True, text=True, timeout=300,
                             check=False)
    install_s = time.monotonic() - t0
    if install.returncode != 0:
        print(install.stdout, install.stderr)
        print(f"FAILED: pip install ./client/python (offline) exited {install.returncode}")
        return 1
    print(f"python3 -m venv --system-site-packages: {venv_s:.1f} s; "
          f"pip install ./client/python (offline): {install_s:.1f} s")
    figures = os.path.join(work, "figures.json")
    env = dict(os.environ, DECIMA_SERVER_BIN=server_bin, DECIMA_CLI_BIN=cli_bin,
               DECIMA_SHARED_DATA=shared, DECIMA_PYCLIENT_SRC=PACKAGE,
               DECIMA_PROTO_DIR=os.path.join(SOURCE, "proto"), DECIMA_PYCLIENT_FIGURES=figures)
    for k in ("DECIMA_SERVER", "DECIMA_TOKEN", "DECIMA_TIMEOUT", "DECIMA_CA_CERT"):
        env.pop(k, None)
    # The tests import the installed package, never the source folder: run from WORK_DIR.
    test = subprocess.run([python, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-rs",
                           "--basetemp", os.path.join(work, "tmp"), HERE] + pytest_args,
                          cwd=work, env=env, timeout=900, check=False)
    if os.path.exists(figures):
        with open(figures, encoding="utf-8") as f:
            print(json.dumps({"venv_seconds": round(venv_s, 1),
                              "pip_install_seconds": round(install_s, 1), **json.load(f)}))
    return test.returncode


if __name__ == "__main__":
    sys.exit(main())
