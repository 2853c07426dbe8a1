"""decima_client: the Python client of decima-server.

Plain setuptools, no pyproject.toml on purpose: pip then builds with the setuptools of the
environment it installs into (Debian's python3-setuptools in a venv made with
--system-site-packages) instead of downloading one into an isolated build environment, so
`pip install ./client/python` works without network. The gRPC stubs are generated from proto/
by gen_stubs.py during build_py, never kept in git.
"""
import os
import sys

from setuptools import setup
from setuptools.command.build_py import build_py

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import gen_stubs  # noqa: E402  (beside this file, not part of the package)


class BuildPyWithStubs(build_py):
    """build_py that also writes decima_client/proto/ from the protos."""

    def run(self):
        super().run()
        try:
            gen_stubs.generate(self.build_lib)
        except gen_stubs.StubError as e:
            raise SystemExit(f"decima_client: {e}") from None


setup(
    name="decima_client",
    version="0.1.0",
    description="Python client of decima-server (gRPC API decima.v1)",
    packages=["decima_client"],
    python_requires=">=3.9",
    # Debian's python3-grpcio and python3-protobuf; pip sees them in a venv made with
    # --system-site-packages and downloads nothing.
    install_requires=["grpcio", "protobuf"],
    extras_require={"numpy": ["numpy"]},
    cmdclass={"build_py": BuildPyWithStubs},
)
