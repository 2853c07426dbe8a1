// Error vocabulary of decima_core: absl::Status / absl::StatusOr, whose codes are the gRPC
// codes, so the server forwards them unchanged. Helpers keep the "check, return" chains short.
#pragma once

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"

#define DECIMA_STATUS_CONCAT_INNER(a, b) a##b
#define DECIMA_STATUS_CONCAT(a, b) DECIMA_STATUS_CONCAT_INNER(a, b)

// Evaluates `expr` (an absl::Status) and returns it from the enclosing function if not OK.
#define DECIMA_RETURN_IF_ERROR(expr)                 \
  do {                                               \
    ::absl::Status decima_status_ = (expr);          \
    if (!decima_status_.ok()) return decima_status_; \
  } while (0)

// Evaluates `rexpr` (an absl::StatusOr<T>); on error returns its status, else moves the value
// into `lhs` (which may be a declaration such as `auto x`).
#define DECIMA_ASSIGN_OR_RETURN(lhs, rexpr) \
  DECIMA_ASSIGN_OR_RETURN_IMPL(DECIMA_STATUS_CONCAT(decima_statusor_, __LINE__), lhs, rexpr)
#define DECIMA_ASSIGN_OR_RETURN_IMPL(tmp, lhs, rexpr) \
  auto tmp = (rexpr);                                 \
  if (!tmp.ok()) return std::move(tmp).status();      \
  lhs = std::move(tmp).value()
