#!/usr/bin/env python3
"""Renders the kustomize base deploy/k8s with `kubectl kustomize` (offline) and checks the
invariants decima-server relies on. Exit 0 = pass, 1 = a violated invariant (each printed),
77 = skipped (kubectl or PyYAML absent).

Usage: k8s_manifest_test.py DEPLOY_K8S_DIR

The checks also run on deliberately broken copies of the rendered manifests, each of which
must be rejected, so a check that cannot fail is itself a failure."""
import copy
import shutil
import subprocess
import sys

try:
    import yaml
except ImportError:
    print("SKIPPED: PyYAML (Debian python3-yaml) is not installed")
    sys.exit(77)


def flag(args, name):
    """The value of --name=V or --name V in a container's args, else None."""
    for i, a in enumerate(args):
        if a.startswith(name + "="):
            return a.split("=", 1)[1]
        if a == name and i + 1 < len(args):
            return args[i + 1]
    return None


def check(docs):
    """Violated invariants of the rendered manifests, as messages (empty = all hold)."""
    errors = []
    by_kind = {}
    for d in docs:
        by_kind.setdefault(d["kind"], []).append(d)
    deployments = by_kind.get("Deployment", [])
    if len(deployments) != 1:
        return [f"expected one Deployment, found {len(deployments)}"]
    dep = deployments[0]
    spec = dep["spec"]
    pod = spec["template"]["spec"]
    labels = spec["template"]["metadata"].get("labels", {})

    if spec.get("replicas", 1) < 2:
        errors.append(f"Deployment replicas {spec.get('replicas', 1)} < 2")
    sel = spec["selector"].get("matchLabels", {})
    if not sel or any(labels.get(k) != v for k, v in sel.items()):
        errors.append(f"Deployment selector {sel} does not match the template labels {labels}")

    containers = [c for c in pod["containers"] if c["name"] == "decima-server"]
    if len(containers) != 1:
        return errors + ["no container named decima-server"]
    c = containers[0]
    args = c.get("args", [])
    listen = flag(args, "--listen")
    if listen is None or ":" not in listen:
        return errors + [f"--listen missing or without a port: {listen}"]
    port = int(listen.rsplit(":", 1)[1])
    if listen.rsplit(":", 1)[0] in ("127.0.0.1", "localhost"):
        errors.append(f"--listen {listen} is loopback: probes and the Service cannot reach it")
    named = {p.get("name"): p["containerPort"] for p in c.get("ports", [])}
    if port not in named.values():
        errors.append(f"--listen port {port} is not a containerPort ({named})")
    for probe in ("readinessProbe", "livenessProbe"):
        p = c.get(probe)
        if not p or "grpc" not in p:
            errors.append(f"{probe} is not a gRPC health probe")
        elif p["grpc"].get("port") != port:
            errors.append(f"{probe} port {p['grpc'].get('port')} != --listen port {port}")

    # The data dir (blobs, volumes, artifacts) is a ReadWriteMany claim mounted at --data-dir.
    data_dir = flag(args, "--data-dir")
    mounts = {m["mountPath"]: m["name"] for m in c.get("volumeMounts", [])}
    volumes = {v["name"]: v for v in pod.get("volumes", [])}
    claims = {p["metadata"]["name"]: p for p in by_kind.get("PersistentVolumeClaim", [])}
    vol = volumes.get(mounts.get(data_dir, ""), {})
    claim = claims.get(vol.get("persistentVolumeClaim", {}).get("claimName", ""))
    if data_dir is None:
        errors.append("--data-dir is not set")
    elif claim is None:
        errors.append(f"--data-dir {data_dir} is not a mounted PersistentVolumeClaim")
    elif "ReadWriteMany" not in claim["spec"].get("accessModes", []):
        errors.append(f"claim {claim['metadata']['name']} is not ReadWriteMany")

    # The store DSN comes from a Secret: a file of a mounted secret volume, or a secretKeyRef.
    env = {e["name"]: e for e in c.get("env", [])}
    store_arg = flag(args, "--store")
    if store_arg is not None:
        errors.append("--store is on the command line (the DSN and its password belong in a Secret)")
    if "DECIMA_STORE_FILE" in env:
        path = env["DECIMA_STORE_FILE"].get("value", "")
        src = [m for m in c.get("volumeMounts", []) if path.startswith(m["mountPath"].rstrip("/") + "/")]
        secret = volumes.get(src[0]["name"], {}).get("secret") if src else None
        if not secret:
            errors.append(f"DECIMA_STORE_FILE {path} is not in a mounted Secret")
    elif "DECIMA_STORE" in env:
        if "secretKeyRef" not in env["DECIMA_STORE"].get("valueFrom", {}):
            errors.append("DECIMA_STORE is not taken from a Secret")
    else:
        errors.append("no DSN: neither DECIMA_STORE_FILE nor DECIMA_STORE is set")

    drain = float(flag(args, "--drain-seconds") or 30)
    grace = pod.get("terminationGracePeriodSeconds", 30)
    if grace <= drain + 2:
        errors.append(f"terminationGracePeriodSeconds {grace} <= --drain-seconds {drain} + 2")

    services = by_kind.get("Service", [])
    if not services:
        errors.append("no Service")
    for s in services:
        ssel = s["spec"].get("selector", {})
        if not ssel or any(labels.get(k) != v for k, v in ssel.items()):
            errors.append(f"Service {s['metadata']['name']} selector {ssel} != template labels")
        for p in s["spec"]["ports"]:
            target = p.get("targetPort", p["port"])
            if named.get(target, target) != port:
                errors.append(f"Service {s['metadata']['name']} targets {target}, not {port}")
    return errors


def mutants(docs):
    """Broken copies of the manifests, one invariant each: (what, docs)."""
    def dep(d):
        return next(x for x in d if x["kind"] == "Deployment")

    def container(d):
        return dep(d)["spec"]["template"]["spec"]["containers"][0]

    out = []
    d = copy.deepcopy(docs)
    container(d)["readinessProbe"]["grpc"]["port"] = 9999
    out.append(("readiness probe on another port", d))
    d = copy.deepcopy(docs)
    c = container(d)
    c["args"] = [a if not a.startswith("--listen") else "--listen=0.0.0.0:6000" for a in c["args"]]
    out.append(("--listen differs from the containerPort", d))
    d = copy.deepcopy(docs)
    next(x for x in d if x["kind"] == "PersistentVolumeClaim")["spec"]["accessModes"] = ["ReadWriteOnce"]
    out.append(("claim ReadWriteOnce", d))
    d = copy.deepcopy(docs)
    c = container(d)
    c["args"] = [a if not a.startswith("--data-dir") else "--data-dir=/tmp/x" for a in c["args"]]
    out.append(("data dir not on the claim", d))
    d = copy.deepcopy(docs)
    c = container(d)
    c["env"] = [{"name": "DECIMA_STORE", "value": "postgresql://u:pw@db/decima"}]
    out.append(("DSN as a plain value", d))
    d = copy.deepcopy(docs)
    dep(d)["spec"]["selector"]["matchLabels"]["app.kubernetes.io/component"] = "other"
    out.append(("selector != template labels", d))
    d = copy.deepcopy(docs)
    dep(d)["spec"]["template"]["spec"]["terminationGracePeriodSeconds"] = 10
    out.append(("grace period below the drain", d))
    d = copy.deepcopy(docs)
    dep(d)["spec"]["replicas"] = 1
    out.append(("one replica", d))
    return out


def main():
    if len(sys.argv) != 2:
        print(__doc__)
        return 2
    kubectl = shutil.which("kubectl")
    if kubectl is None:
        print("SKIPPED: kubectl is not installed (it renders the kustomize base offline)")
        return 77
    r = subprocess.run([kubectl, "kustomize", sys.argv[1]], capture_output=True, text=True,
                       timeout=120)
    if r.returncode != 0:
        print(f"kubectl kustomize {sys.argv[1]} failed:\n{r.stderr}")
        return 1
    docs = [d for d in yaml.safe_load_all(r.stdout) if d]
    kinds = sorted(d["kind"] for d in docs)
    print(f"rendered {len(docs)} objects: {', '.join(kinds)}")
    errors = check(docs)
    for e in errors:
        print(f"FAIL: {e}")
    for what, broken in mutants(docs):
        if not check(broken):
            errors.append(what)
            print(f"FAIL: the checks accept a broken manifest ({what})")
    if not errors:
        print("PASS: port = --listen, gRPC probes on it, RWX claim at --data-dir, DSN from a "
              "Secret, selectors = template labels, grace > drain, >= 2 replicas")
    return 1 if errors else 0


if __name__ == "__main__":
    sys.exit(main())
