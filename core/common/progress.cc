#include "core/common/progress.h"

#include "absl/strings/str_cat.h"

namespace decima {

absl::Status CheckCancelled(const CancelToken* token, const char* stage) {
  if (token != nullptr && token->cancelled()) {
    return absl::CancelledError(absl::StrCat(stage, ": cancelled"));
  }
  return absl::OkStatus();
}

}  // namespace decima
