#!/usr/bin/env bash
# Installs every Debian 12 package that Decima's build, tests, benchmarks and demo need.
# Idempotent and non-interactive: packages already present are skipped by apt itself.
# Usage: deploy/install-deps.sh [--with-demo-data]
set -euo pipefail

packages=(
  # toolchain (ninja for the sanitizer builds); ccache lets repeated builds reuse compiled
  # objects instead of compiling again
  build-essential cmake ninja-build pkg-config git ca-certificates ccache
  # service: gRPC + Protobuf (Debian ships CMake configs), abseil for Status/StatusOr
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler libabsl-dev
  # core numerics and logging
  libeigen3-dev libspdlog-dev libfmt-dev
  # readers and writers of outside formats
  zlib1g-dev liblzma-dev libpng-dev libgdcm-dev
  # job store, CLI parsing, JSON
  libsqlite3-dev libcli11-dev nlohmann-json3-dev
  # the PostgreSQL job store of replicas (libpqxx), and the real PostgreSQL 15 its tests and
  # decima-scale-bench start in a temp folder; python3-yaml parses the rendered k8s manifests
  libpqxx-dev postgresql postgresql-client python3-yaml
  # tests and benchmarks; openssl (the command) makes the throwaway CA and certificates of the
  # TLS / mutual TLS end-to-end tests and of decima-service-bench --security
  libgtest-dev libgmock-dev libbenchmark-dev openssl
  # libFuzzer targets (DECIMA_FUZZ=ON, clang only): tests/fuzz, tests/core/io/io_fuzz
  clang libclang-rt-14-dev
  # /usr/bin/time: tests/fuzz/campaign.sh reports the CPU seconds each fuzz target got
  time
  # independent tools that prove our files are readable by others
  python3 python3-vtk9 python3-numpy gmsh
  # a real browser (headless) that opens report.html (and draws its WebGL 3D view) in
  # tests/core/pipeline/report_test.cc and tests/e2e/cli_e2e_test.cc
  chromium
  # the real MRI the demo and tests use
  mricron-data
  # PACS side (issue 13): DCMTK for the C-STORE receiver/sender and the DICOM SEG writer
  # (dcmnet, dcmseg, dcmiod), libcurl for STOW-RS and the CLI's WADO-RS pull
  libdcmtk-dev libcurl4-openssl-dev
  # ... and the real PACS and checkers of the PACS end-to-end test: Orthanc with its DICOMweb
  # plugin, dciodvfy (dicom3tools) to validate the SEG, pydicom to read it back, dcmtk tools
  orthanc orthanc-dicomweb dicom3tools python3-pydicom dcmtk
  # the Python client (client/python): Debian's gRPC and Protobuf runtimes (a venv made with
  # --system-site-packages uses them, so `pip install ./client/python` downloads nothing), venv
  # and setuptools/wheel to build the package offline, pytest for its tests; its stubs are made
  # by protoc and grpc_python_plugin (protobuf-compiler, protobuf-compiler-grpc above)
  python3-grpcio python3-protobuf python3-venv python3-setuptools python3-wheel python3-pytest
)

# The report's 3D view: npm installs the pinned three.js and esbuild of core/pipeline/web (npm ci,
# package-lock.json) at build time and node runs esbuild to bundle them into the page. A machine
# with its own npm and node keeps them: NodeSource's nodejs bundles npm and conflicts with
# Debian's npm package, so asking apt for it there would fail the whole install.
if ! command -v npm >/dev/null || ! command -v node >/dev/null; then
  packages+=(npm nodejs)
fi

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if [ ${#missing[@]} -eq 0 ]; then
  echo "install-deps: all ${#packages[@]} packages present"
  exit 0
fi

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
echo "install-deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
