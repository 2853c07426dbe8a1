#!/usr/bin/python3
"""The ctest driver of the decima_client tests, the way a user installs the package.

  run_tests.py install VENV_DIR
      A fresh venv that sees Debian's python3-grpcio and python3-protobuf
      (--system-site-packages), then `pip install ./client/python` of a copy of client/python
      with proto/ beside it (as in a checkout, so the build leaves nothing in the source tree),
      with every package index, find-links and pip config switched off: the install is proven
      to need no network. Prints the seconds of both steps.
  run_tests.py test VENV_DIR SERVER_BIN CLI_BIN SHARED_DATA [--require FILE] [pytest args...]
      pytest (Debian's python3-pytest) in that venv, against the real decima-server and CLI.

Exit 77 (ctest: skipped) when python3-grpcio, python3-protobuf, python3-pytest or venv is
missing, when --require names a file that is not in SHARED_DATA, or when every test skipped;
else 0, pip's failure (1) or pytest's exit code. When the CT head ran, its figures are printed
as one JSON line.
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


def missing_package():
    for module, package in (("grpc", "python3-grpcio"), ("google.protobuf", "python3-protobuf"),
                            ("pytest", "python3-pytest"), ("venv", "python3-venv"),
                            ("ensurepip", "python3-venv")):
        if importlib.util.find_spec(module) is None:
            return package
    return None


def install(work):
    shutil.rmtree(work, ignore_errors=True)
    os.makedirs(work)
    src = os.path.join(work, "src")
    shutil.copytree(PACKAGE, os.path.join(src, "client", "python"),
                    ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    shutil.copytree(os.path.join(SOURCE, "proto"), os.path.join(src, "proto"))
    venv = os.path.join(work, "venv")
    t0 = time.monotonic()
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", venv], check=True,
                   timeout=300)
    venv_s = time.monotonic() - t0
    offline = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")}
    offline.update(PIP_NO_INDEX="1", PIP_CONFIG_FILE=os.devnull,
                   PIP_DISABLE_PIP_VERSION_CHECK="1")
    t0 = time.monotonic()
    pip = subprocess.run([os.path.join(venv, "bin", "pip"), "install", "./client/python"],
                         cwd=src, env=offline, capture_output=True, text=True, timeout=300,
                         check=False)
    install_s = time.monotonic() - t0
    if pip.returncode != 0:
        print(pip.stdout, pip.stderr)
        print(f"FAILED: pip install ./client/python (offline) exited {pip.returncode}")
        return 1
    print(json.dumps({"venv_seconds": round(venv_s, 1),
                      "pip_install_seconds": round(install_s, 1)}))
    return 0


def test(work, server_bin, cli_bin, shared, args):
    if args[:1] == ["--require"] and len(args) >= 2:
        required = os.path.join(shared, args[1])
        if not os.path.isfile(required):
            print(f"SKIPPED: {required} is absent (the shared data beside the checkout)")
            return SKIP
        args = args[2:]
    python = os.path.join(work, "venv", "bin", "python")
    if not os.path.exists(python):
        print(f"FAILED: {python} is missing: run `run_tests.py install {work}` first (ctest: "
              "python_client_install)")
        return 1
    tmp = os.path.join(work, "tmp-" + str(os.getpid()))
    figures = os.path.join(tmp, "figures.json")
    os.makedirs(tmp)
    env = dict(os.environ, DECIMA_SERVER_BIN=server_bin, DECIMA_CLI_BIN=cli_bin,
               DECIMA_SHARED_DATA=shared, DECIMA_PYCLIENT_SRC=PACKAGE,
               DECIMA_PROTO_DIR=os.path.join(SOURCE, "proto"), DECIMA_PYCLIENT_FIGURES=figures)
    for k in ("DECIMA_SERVER", "DECIMA_TOKEN", "DECIMA_TIMEOUT", "DECIMA_CA_CERT",
              "DECIMA_TLS_CERT", "DECIMA_TLS_KEY"):
        env.pop(k, None)
    # The tests import the installed package, never the source folder: run from the temp dir.
    run = subprocess.run([python, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-rs",
                          "--basetemp", os.path.join(tmp, "pytest")] + args,
                         cwd=tmp, env=env, timeout=900, check=False)
    if os.path.exists(figures):
        with open(figures, encoding="utf-8") as f:
            print(json.dumps(json.load(f)))
    if run.returncode == 0:
        shutil.rmtree(tmp, ignore_errors=True)
    return run.returncode


def main():
    argv = sys.argv[1:]
    if argv[:1] == ["install"] and len(argv) == 2:
        package = missing_package()
        if package:
            print(f"SKIPPED: {package} is not installed (deploy/install-deps.sh installs it)")
            return SKIP
        return install(os.path.abspath(argv[1]))
    if argv[:1] == ["test"] and len(argv) >= 5:
        package = missing_package()
        if package:
            print(f"SKIPPED: {package} is not installed (deploy/install-deps.sh installs it)")
            return SKIP
        work, server_bin, cli_bin, shared = (os.path.abspath(a) for a in argv[1:5])
        return test(work, server_bin, cli_bin, shared, argv[5:])
    sys.exit(__doc__)


if __name__ == "__main__":
    sys.exit(main())
