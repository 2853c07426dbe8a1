#!/usr/bin/env python3
"""Independent check of Decima's .msh and .mesh files with the gmsh program.

  check_gmsh.py GMSH INPUT OUTPUT_MSH

Runs `GMSH INPUT -0 -format msh22 -o OUTPUT_MSH` (gmsh reads the file with its own reader and
writes it back in the simple MSH 2.2 ASCII layout), fails if gmsh reports an error, then prints
one "key value" line per fact about what gmsh saw: node count and sum of |coordinates|,
tetrahedron count, the sum over tets of |coordinates| of their nodes and their smallest and
total signed volume (facts that survive gmsh's renumbering of nodes), tets per physical tag and
per elementary tag, and physical names. (Without -save_all gmsh keeps only elements in physical
groups when the file has any, so the physical counts also prove every tet is in one.)
"""
import subprocess
import sys
from collections import Counter


def main(argv):
    if len(argv) != 4:
        sys.exit(__doc__)
    gmsh, src, out = argv[1:]
    run = subprocess.run([gmsh, src, "-0", "-format", "msh22", "-o", out],
                         capture_output=True, text=True, timeout=300)
    log = run.stdout + run.stderr
    if run.returncode != 0 or "Error" in log:
        sys.exit(f"gmsh failed on {src} (exit {run.returncode}):\n{log}")
    with open(out) as f:
        lines = f.read().split("\n")
    i = 0
    physical, elementary, names = Counter(), Counter(), {}
    nodes = tets = others = 0
    coords = {}
    tet_nodes = []
    while i < len(lines):
        line = lines[i].strip()
        if line == "$PhysicalNames":
            n = int(lines[i + 1])
            for k in range(n):
                dim, tag, name = lines[i + 2 + k].split(maxsplit=2)
                names[int(tag)] = (int(dim), name.strip('"'))
            i += n + 2
        elif line == "$Nodes":
            nodes = int(lines[i + 1])
            for k in range(nodes):
                fields = lines[i + 2 + k].split()
                coords[int(fields[0])] = [float(x) for x in fields[1:4]]
            i += nodes + 2
        elif line == "$Elements":
            n = int(lines[i + 1])
            for k in range(n):
                f = [int(x) for x in lines[i + 2 + k].split()]
                etype, ntags = f[1], f[2]
                if etype != 4:
                    others += 1
                    continue
                tets += 1
                physical[f[3]] += 1
                elementary[f[4]] += 1
                tet_nodes.append(f[3 + ntags:])
            i += n + 2
        else:
            i += 1
    print("nodes", nodes)
    print("coord_abs_sum", repr(sum(abs(c) for p in coords.values() for c in p)))
    print("tets", tets)
    print("other_elements", others)
    tet_abs, min_vol, total_vol = 0.0, float("inf"), 0.0
    for t in tet_nodes:
        p = [coords[n] for n in t]
        tet_abs += sum(abs(c) for q in p for c in q)
        a, b, c = ([p[k][d] - p[0][d] for d in range(3)] for k in (1, 2, 3))
        vol = (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) +
               a[2] * (b[0] * c[1] - b[1] * c[0])) / 6.0
        min_vol, total_vol = min(min_vol, vol), total_vol + vol
    print("tet_coord_abs_sum", repr(tet_abs))
    print("min_volume", repr(min_vol))
    print("total_volume", repr(total_vol))
    for tag, count in sorted(physical.items()):
        print("physical", tag, count)
    for tag, count in sorted(elementary.items()):
        print("elementary", tag, count)
    for tag, (dim, name) in sorted(names.items()):
        print("name", dim, tag, name)


if __name__ == "__main__":
    main(sys.argv)
