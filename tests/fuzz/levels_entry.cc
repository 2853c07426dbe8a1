#include <string_view>

#include "core/simplify/levels.h"
#include "core/simplify/levels_io.h"
#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_require.h"

namespace decima::fuzz {

int LevelsEntry(const uint8_t* data, size_t size) {
  SetLastInputAccepted(false);
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  auto levels = ParseLevels(bytes);
  if (!levels.ok()) return 0;
  Require(ValidateLevels(*levels).ok(), "a record ParseLevels accepts is a valid simplicial map");
  Require(levels->deepest_reduction() <= 1.0, "collapses delete at most the base cells");
  // What the writer makes of it reads back the same (zlib may pack it differently).
  auto again = ParseLevels(SerializeLevels(*levels));
  Require(again.ok(), "a parsed record serializes to a file ParseLevels accepts");
  Require(again->removed_vertex == levels->removed_vertex && again->survivor == levels->survivor &&
              again->cells_deleted == levels->cells_deleted &&
              again->base_vertices == levels->base_vertices &&
              again->base_cells == levels->base_cells &&
              again->base_digest == levels->base_digest && again->exhausted == levels->exhausted &&
              again->refit_iterations == levels->refit_iterations,
          "level record round trip");
  SetLastInputAccepted(true);
  return 0;
}

}  // namespace decima::fuzz
