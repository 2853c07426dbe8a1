// FidelityMetrics as JSON: the one spelling of the metrics shared by a job's metrics.json and
// decima-bench. Non-finite values (PSNR of an exact copy) become null.
#pragma once

#include <nlohmann/json.hpp>

#include "core/metrics/fidelity.h"

namespace decima {

nlohmann::ordered_json FidelityToJson(const FidelityMetrics& m);

}  // namespace decima
