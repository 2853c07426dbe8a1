"""The installed stubs are exactly what the checkout's protos generate (never stale, never
edited): generated again here from proto/ with the same protoc and grpc_python_plugin, byte for
byte, plus the sha256 of each proto recorded at build time."""
import filecmp
import importlib.util
import os
import shutil

import pytest

import decima_client.proto as installed


def _gen_stubs():
    src = os.environ.get("DECIMA_PYCLIENT_SRC", "")
    path = os.path.join(src, "gen_stubs.py")
    if not os.path.isfile(path):
        pytest.skip("DECIMA_PYCLIENT_SRC does not hold gen_stubs.py (run through ctest)")
    spec = importlib.util.spec_from_file_location("gen_stubs", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def differences(generated_dir, installed_dir):
    """Names of the generated files missing from or different in installed_dir."""
    out = []
    for name in sorted(os.listdir(generated_dir)):
        if not name.endswith(".py"):
            continue
        theirs = os.path.join(installed_dir, name)
        if not os.path.isfile(theirs) or not filecmp.cmp(os.path.join(generated_dir, name),
                                                           theirs, shallow=False):
            out.append(name)
    return out


def test_installed_stubs_are_what_the_protos_generate(tmp_path):
    gen = _gen_stubs()
    generated = gen.generate(str(tmp_path))
    installed_dir = os.path.dirname(installed.__file__)
    assert differences(generated, installed_dir) == []
    assert installed.PROTO_SHA256 == gen.proto_digests(gen.proto_dir())
    assert sorted(installed.PROTO_SHA256) == gen.protos(gen.proto_dir())
    assert "jobs.proto" in installed.PROTO_SHA256


def test_a_changed_proto_is_caught(tmp_path):
    # The check above can fail: a proto with one more field generates different stubs.
    gen = _gen_stubs()
    protos = tmp_path / "proto"
    shutil.copytree(gen.proto_dir(), protos)
    jobs = protos / "decima" / "v1" / "jobs.proto"
    jobs.write_text(jobs.read_text().replace("message Heartbeat {}",
                                             "message Heartbeat { int32 extra = 1; }"))
    generated = gen.generate(str(tmp_path / "out"), str(protos))
    # The module itself and the recorded digest in __init__.py.
    assert differences(generated, os.path.dirname(installed.__file__)) == ["__init__.py",
                                                                          "jobs_pb2.py"]
    assert gen.proto_digests(str(protos))["jobs.proto"] != installed.PROTO_SHA256["jobs.proto"]


def test_a_new_proto_file_is_generated_too(tmp_path):
    gen = _gen_stubs()
    protos = tmp_path / "proto"
    shutil.copytree(gen.proto_dir(), protos)
    (protos / "decima" / "v1" / "later.proto").write_text(
        'syntax = "proto3";\npackage decima.v1;\nmessage Later { int32 x = 1; }\n')
    generated = gen.generate(str(tmp_path / "out"), str(protos))
    assert os.path.isfile(os.path.join(generated, "later_pb2.py"))
    assert "later_pb2.py" in differences(generated, os.path.dirname(installed.__file__))


def test_every_rpc_of_the_protos_has_a_stub():
    from decima_client.proto import (artifacts_pb2, artifacts_pb2_grpc, jobs_pb2, jobs_pb2_grpc,
                                     uploads_pb2, uploads_pb2_grpc, volumes_pb2,
                                     volumes_pb2_grpc)

    for pb2, grpc_mod in ((jobs_pb2, jobs_pb2_grpc), (volumes_pb2, volumes_pb2_grpc),
                          (uploads_pb2, uploads_pb2_grpc), (artifacts_pb2, artifacts_pb2_grpc)):
        for service in pb2.DESCRIPTOR.services_by_name.values():
            stub = getattr(grpc_mod, service.name + "Stub")(_NoChannel())
            for method in service.methods:
                assert hasattr(stub, method.name), f"{service.name}.{method.name}"


class _NoChannel:
    """Enough of a grpc.Channel for a stub's constructor (it only builds callables)."""

    def __getattr__(self, _):
        return lambda *a, **k: None
