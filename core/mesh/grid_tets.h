// The 5-tet decomposition of a voxel grid as a function of the cell id, so that a stage can read
// the cells of the grid mesh without holding them (16 bytes per tet; issue 30).
//
// Layout (the one Tetrahedralize writes): vertex v = i + nx * (j + ny * k) is the voxel centre
// (i, j, k); cube c = i + (nx-1) * (j + (ny-1) * k) owns tets 5c .. 5c+4. Each cube is a central
// tet and four corner tets; the split alternates with the parity of (i + j + k) so that shared
// face diagonals agree, and every tet is positively oriented in physical space (all of them are
// reordered when the index-to-physical map reverses orientation).
#pragma once

#include <cstdint>

namespace decima {

class GridTets {
 public:
  GridTets() = default;
  // nx, ny, nz >= 2; `flip`: the index-to-physical map has a negative determinant.
  GridTets(int64_t nx, int64_t ny, int64_t nz, bool flip);

  int64_t nx() const { return nx_; }
  int64_t ny() const { return ny_; }
  int64_t nz() const { return nz_; }
  bool flip() const { return flip_; }
  int64_t vertex_count() const { return nx_ * ny_ * nz_; }
  int64_t tet_count() const { return 5 * (nx_ - 1) * (ny_ - 1) * (nz_ - 1); }

  // A tet with its cube decoded, for walks from tet to tet without a division per step (the
  // renderer's ray casting): At(t) decodes once, Step moves across a face.
  struct Place {
    int64_t cube = 0;
    int32_t base = 0;  // vertex id of the cube's corner (i, j, k)
    int32_t ijk[3] = {};
    int s = 0, parity = 0;
  };
  Place At(int64_t t) const {
    Place p;
    p.cube = t / 5;
    p.s = static_cast<int>(t - 5 * p.cube);
    const int64_t jk = p.cube / (nx_ - 1);
    p.ijk[0] = static_cast<int32_t>(p.cube - jk * (nx_ - 1));
    p.ijk[2] = static_cast<int32_t>(jk / (ny_ - 1));
    p.ijk[1] = static_cast<int32_t>(jk - int64_t{p.ijk[2]} * (ny_ - 1));
    p.base = static_cast<int32_t>(p.ijk[0] + nx_ * (p.ijk[1] + ny_ * p.ijk[2]));
    p.parity = (p.ijk[0] + p.ijk[1] + p.ijk[2]) & 1;
    return p;
  }
  int64_t Id(const Place& p) const { return 5 * p.cube + p.s; }
  void Cell(const Place& p, int32_t out[4]) const {
    const int32_t* offset = offsets_[p.parity][p.s];
    for (int q = 0; q < 4; ++q) out[q] = p.base + offset[q];
  }
  // Moves `p` to the tet across its face q; false (p unchanged) when that face is on the hull.
  bool Step(Place& p, int q) const {
    const Across& a = across_[p.parity][p.s][q];
    if (a.axis >= 0) {
      const int32_t at = p.ijk[a.axis];
      if (a.dir > 0 ? at == last_[a.axis] : at == 0) return false;
      p.ijk[a.axis] = at + a.dir;
      p.cube += a.dir * cube_stride_[a.axis];
      p.base += a.dir * vertex_stride_[a.axis];
      p.parity ^= 1;
    }
    p.s = a.s;
    return true;
  }

  // The four vertices of tet t (0 <= t < tet_count()), in the order Tetrahedralize stores them.
  void Cell(int64_t t, int32_t out[4]) const { Cell(At(t), out); }

  // f(t, cell) for t0 <= t < t1 in increasing t, cell being Cell(t): the place is stepped from
  // cube to cube instead of decoded from every id, for the passes that read all cells in order
  // (three 64-bit divisions per cell made them slower than reading stored cells).
  template <typename F>
  void ForEachCell(int64_t t0, int64_t t1, F&& f) const {
    if (t0 >= t1) return;
    Place p = At(t0);
    int32_t out[4];
    for (int64_t t = t0; t < t1; ++t) {
      Cell(p, out);
      f(t, static_cast<const int32_t*>(out));
      if (++p.s < 5) continue;
      // Next cube: one vertex on along x; past a row's last cube also over the row's last vertex,
      // past a slice's last row also over the slice's last row of vertices.
      p.s = 0;
      ++p.cube;
      ++p.base;
      p.parity ^= 1;
      if (++p.ijk[0] <= last_[0]) continue;
      p.ijk[0] = 0;
      ++p.base;
      if (++p.ijk[1] > last_[1]) {
        p.ijk[1] = 0;
        ++p.ijk[2];
        p.base += vertex_stride_[1];
      }
      p.parity = (p.ijk[1] + p.ijk[2]) & 1;
    }
  }

  // The tet across face q (the face opposite vertex q of Cell(t)) of tet t, or -1 when that face
  // is on the hull of the grid. The same tet as matching faces of the materialized mesh gives
  // (RenderableMesh's adjacency, TetAcrossFace), without holding any per-tet array.
  int64_t Neighbour(int64_t t, int q) const {
    Place p = At(t);
    return Step(p, q) ? Id(p) : -1;
  }

 private:
  // Where face q of tet s of a cube leads: tet `s` of the same cube (axis -1) or of the next cube
  // along `axis` in direction `dir` (+1 / -1).
  struct Across {
    int8_t axis = -1, dir = 0, s = 0;
  };

  int64_t nx_ = 0, ny_ = 0, nz_ = 0;
  bool flip_ = false;
  int32_t offsets_[2][5][4] = {};
  Across across_[2][5][4] = {};
  int64_t cube_stride_[3] = {};
  int32_t vertex_stride_[3] = {};
  int32_t last_[3] = {};  // the largest cube index along each axis
};

}  // namespace decima
