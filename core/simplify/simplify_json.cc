#include "core/simplify/simplify_json.h"

namespace decima {

nlohmann::ordered_json SimplifyResultToJson(const SimplifyResult& result,
                                            const SimplifyOptions& options,
                                            int64_t vertices_before) {
  nlohmann::ordered_json j = {{"policy", SimplifyPolicyName(options.policy)},
                              {"target_reduction", options.target_reduction},
                              {"achieved_reduction", result.achieved_reduction},
                              {"reached_target", result.reached_target},
                              {"stop_reason", StopReasonName(result.stop_reason)},
                              {"stop_message", result.stop_message},
                              {"passes", result.passes},
                              {"cells_before", result.input_cells},
                              {"cells_after", result.output_cells},
                              {"vertices_before", vertices_before},
                              {"vertices_after", result.mesh.vertex_count()}};
  if (options.policy == SimplifyPolicy::kField) {
    j["interfaces"] = InterfaceModeName(options.interfaces);
  }
  return j;
}

}  // namespace decima
