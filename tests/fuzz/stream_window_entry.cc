#include <map>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "core/mesh/tetrahedralize.h"
#include "core/simplify/stream.h"
#include "core/volume/phantom.h"
#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_require.h"

namespace decima::fuzz {
namespace {

constexpr int kSlab = 4;

// A small grid (13 cube layers: 4 windows a pass in slabs of 4), the run's own records and mesh.
struct Fixture {
  TetMesh mesh;
  SimplifyOptions options;
  std::map<std::pair<int, int64_t>, std::string> records;
  SimplifyResult whole;
};

const Fixture& TheFixture() {
  static const Fixture* f = [] {
    auto* x = new Fixture;
    HeadPhantomOptions o;
    o.dims = {10, 9, 14};
    o.noise_sigma = 20;
    o.seed = 3;
    auto p = MakeHeadPhantom(o);
    Require(p.ok(), "the fixture's phantom");
    const std::vector<float> distance(p->labels.voxel_count(), 1.5f);
    TetrahedralizeOptions t;
    t.labels = &p->labels;
    t.interface_distance = distance.data();
    auto mesh = Tetrahedralize(p->image, t);
    Require(mesh.ok(), "the fixture's mesh");
    x->mesh = *std::move(mesh);
    x->options.policy = SimplifyPolicy::kField;
    x->options.target_reduction = 0.8;
    x->options.threads = 1;
    StreamJournal j;
    j.save = [x](int pass, int64_t window, const std::string& r) {
      x->records[{pass, window}] = r;
    };
    auto whole = SimplifyStreamed(x->mesh, x->options, kSlab, nullptr, nullptr, &j);
    Require(whole.ok() && j.windows_per_pass == 4, "the fixture's run");
    // The seeds read back the records of pass 0 (measuring) and pass 1.
    Require(x->records.count({1, 3}) == 1, "the fixture runs two passes");
    x->whole = *std::move(whole);
    return x;
  }();
  return *f;
}

}  // namespace

int StreamWindowEntry(const uint8_t* data, size_t size) {
  SetLastInputAccepted(false);
  if (size == 0) return 0;
  const Fixture& f = TheFixture();
  const int pass = data[0] & 3;
  std::vector<std::string> records;
  std::string_view in(reinterpret_cast<const char*>(data) + 1, size - 1);
  if (data[0] & 4) {
    for (int64_t k = 0; k < 4; ++k) {
      auto it = f.records.find({pass, k});
      if (it == f.records.end()) break;
      records.push_back(it->second);
    }
    for (size_t i = 0; i + 4 <= in.size() && !records.empty(); i += 4) {
      std::string& r = records[uint8_t(in[i]) % records.size()];
      const size_t at = (uint8_t(in[i + 1]) | size_t(uint8_t(in[i + 2])) << 8) % r.size();
      r[at] = in[i + 3];
    }
  } else {
    while (!in.empty()) {
      const size_t at = in.find(kFileSeparator);
      records.emplace_back(in.substr(0, at));
      if (at == std::string_view::npos) break;
      in.remove_prefix(at + kFileSeparator.size());
    }
  }
  StreamJournal j;
  j.load = [&](int p, int64_t window) -> std::optional<std::string> {
    if (p != pass || window >= int64_t(records.size())) return std::nullopt;
    return records[window];
  };
  auto r = SimplifyStreamed(f.mesh, f.options, kSlab, nullptr, nullptr, &j);
  if (!r.ok()) return 0;
  const TetMesh& m = r->mesh;
  const int64_t nv = m.vertex_count();
  Require(int64_t(m.positions.size()) == 3 * nv && m.tets.size() % 4 == 0 &&
              m.cell_regions.size() == m.tets.size() / 4 && int64_t(m.scalars.size()) == nv &&
              int64_t(m.labels.size()) == nv,
          "the streamed mesh's array sizes agree");
  for (int32_t v : m.tets) Require(v >= 0 && v < nv, "cell indices in range");
  Require(r->vertex_map.size() == f.mesh.positions.size() / 3, "a vertex map of the input");
  for (int32_t v : r->vertex_map) Require(v >= -1 && v < nv, "vertex map in range");
  if (!(data[0] & 4) || size == 1) {
    // The run's own records, whole: the run's own mesh.
    if (data[0] & 4) {
      Require(j.resumed_windows == int64_t(records.size()), "the real records are read back");
      Require(m.tets == f.whole.mesh.tets && m.positions == f.whole.mesh.positions &&
                  r->vertex_map == f.whole.vertex_map,
              "read back, the run's own records give its mesh");
    }
  }
  SetLastInputAccepted(j.resumed_windows > 0);
  return 0;
}

}  // namespace decima::fuzz
