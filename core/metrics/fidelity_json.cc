#include "core/metrics/fidelity_json.h"

#include <cmath>

namespace decima {

nlohmann::ordered_json FidelityToJson(const FidelityMetrics& m) {
  using Json = nlohmann::ordered_json;
  auto finite = [](double v) { return std::isfinite(v) ? Json(v) : Json(nullptr); };
  Json j;
  j["vertices"] = m.vertices;
  j["cells"] = m.cells;
  j["coverage"] = m.coverage;
  j["rmse"] = m.rmse;
  j["psnr_db"] = finite(m.psnr_db);
  j["max_abs_error"] = m.max_abs_error;
  j["value_range"] = m.value_range;
  Json dice = Json::array();
  for (const RegionDice& d : m.dice) dice.push_back({{"label", d.label}, {"dice", d.dice}});
  j["dice"] = dice;
  j["mean_dice"] = m.mean_dice;
  j["label_mismatch"] = m.label_mismatch;
  j["interface_rmse"] = m.interface_rmse;
  j["interface_distance_max_voxels"] = m.interface_distance_max_voxels;
  j["interface_distance_mean_voxels"] = m.interface_distance_mean_voxels;
  j["interface_vertices"] = m.interface_vertices;
  j["feature_vertices"] = m.feature_vertices;
  j["feature_vertices_moved"] = m.feature_vertices_moved;
  j["feature_vertices_removed"] = m.feature_vertices_removed;
  j["inverted_cells"] = m.inverted_cells;
  j["degenerate_cells"] = m.degenerate_cells;
  j["min_dihedral_deg"] = m.min_dihedral_deg;
  j["boundary_faces"] = m.boundary_faces;
  j["interior_faces"] = m.interior_faces;
  j["nonmanifold_faces"] = m.nonmanifold_faces;
  j["folded_faces"] = m.folded_faces;
  j["boundary_area_mm2"] = m.boundary_area_mm2;
  j["manifold"] = m.manifold;
  j["mesh_bytes"] = m.mesh_bytes;
  j["voxel_bytes"] = m.voxel_bytes;
  j["bytes_ratio"] = m.bytes_ratio;
  return j;
}

}  // namespace decima
