"""Generates the gRPC stubs of decima_client from the repository's proto/ folder.

Used by setup.py at build time (so an installed package always carries stubs made from the
protos it was built from) and by the test that checks an installed package against the protos
(tests/test_stubs.py). Nothing it writes is kept in git or edited by hand.

The protos are mapped to the virtual path decima_client/proto/ (protoc's -IVIRTUAL=DISK), so
the generated modules import each other as decima_client.proto.* and the package adds no
top-level `decima` package to site-packages.

usage: python3 gen_stubs.py OUT_DIR [PROTO_DIR]
"""
import hashlib
import os
import shutil
import subprocess
import sys

# The public API is every file of proto/decima/v1, found anew at each build so that a proto
# added there is never missing from the package (the server reflection proto is the server's).
API_DIR = ("decima", "v1")
PACKAGE_PATH = "decima_client/proto"

HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_PROTO_DIR = os.path.normpath(os.path.join(HERE, "..", "..", "proto"))


class StubError(Exception):
    """The stubs could not be generated; the message says which tool or file and why."""


def proto_dir():
    """The proto/ folder: $DECIMA_PROTO_DIR, else the checkout's proto/ beside client/."""
    return os.environ.get("DECIMA_PROTO_DIR", DEFAULT_PROTO_DIR)


def protos(root):
    """The names of the .proto files of ROOT/decima/v1, sorted."""
    v1 = os.path.join(root, *API_DIR)
    return sorted(n for n in os.listdir(v1) if n.endswith(".proto")) if os.path.isdir(v1) else []


def proto_digests(root):
    """{"jobs.proto": sha256 hex, ...} of the protos the stubs are made from."""
    out = {}
    for name in protos(root):
        path = os.path.join(root, "decima", "v1", name)
        with open(path, "rb") as f:
            out[name] = hashlib.sha256(f.read()).hexdigest()
    return out


def generate(out_dir, root=None):
    """Writes OUT_DIR/decima_client/proto/{*_pb2.py, *_pb2_grpc.py, __init__.py}.

    Raises StubError naming the missing tool or proto file, or protoc's own message.
    """
    root = root or proto_dir()
    v1 = os.path.join(root, *API_DIR)
    names = protos(root)
    # The package's own modules import these; without them the protos are not Decima's.
    missing = [n for n in ("errors.proto", "jobs.proto", "uploads.proto", "volumes.proto",
                           "artifacts.proto") if n not in names]
    if missing:
        raise StubError(
            f"{v1}: missing {', '.join(missing)}; build from a Decima checkout "
            "(client/python beside proto/) or set DECIMA_PROTO_DIR to its proto/ folder")
    protoc = shutil.which("protoc")
    plugin = shutil.which("grpc_python_plugin")
    if protoc is None or plugin is None:
        raise StubError("protoc and grpc_python_plugin are needed to build decima_client "
                        "(Debian: apt-get install protobuf-compiler protobuf-compiler-grpc)")
    target = os.path.join(out_dir, PACKAGE_PATH)
    os.makedirs(target, exist_ok=True)
    cmd = [protoc, f"-I{PACKAGE_PATH}={v1}", f"--python_out={out_dir}",
           f"--grpc_python_out={out_dir}", f"--plugin=protoc-gen-grpc_python={plugin}"]
    cmd += [os.path.join(v1, n) for n in names]
    run = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if run.returncode != 0:
        raise StubError(f"{' '.join(cmd)} failed ({run.returncode}): {run.stderr.strip()}")
    digests = proto_digests(root)
    with open(os.path.join(target, "__init__.py"), "w", encoding="utf-8") as f:
        f.write('"""Stubs generated from proto/decima/v1 by gen_stubs.py at build time. '
                'Do not edit."""\n')
        f.write("# sha256 of each proto the stubs were generated from\n")
        f.write("PROTO_SHA256 = {\n")
        for name, digest in digests.items():
            f.write(f'    "{name}": "{digest}",\n')
        f.write("}\n")
    return target


if __name__ == "__main__":
    if len(sys.argv) not in (2, 3):
        sys.exit(__doc__)
    try:
        print(generate(sys.argv[1], sys.argv[2] if len(sys.argv) == 3 else None))
    except StubError as e:
        sys.exit(f"gen_stubs: {e}")
