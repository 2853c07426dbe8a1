// Lossless binary records of plain values and arrays (floats by their bits, integers in the
// machine's byte order): the stage checkpoints (core/pipeline/checkpoint.h) and the streamed
// simplifier's window records (core/simplify/stream.h) are written and read back with these, on
// the same architecture, so a resumed run gives byte-identical results.
//
// A record is trusted only after a checksum its container holds; the reader still never reads
// past its bytes and refuses an array larger than what is left, so a damaged record fails with
// the name of the field instead of allocating or crashing.
#pragma once

#include <cstdint>
#include <cstring>
#include <functional>
#include <string>
#include <string_view>
#include <type_traits>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace decima {

class ByteWriter {
 public:
  // Bytes handed over as they are written, in order, instead of kept: a record of hundreds of MB
  // (a clinical scan's simplified mesh) goes to its file without a copy in memory. Small values
  // are gathered up to kSinkBlock first; an array's bytes go out from the array itself.
  using Sink = std::function<void(std::string_view bytes)>;
  static constexpr size_t kSinkBlock = size_t{1} << 20;

  ByteWriter() = default;
  explicit ByteWriter(Sink sink) : sink_(std::move(sink)) {}

  template <typename T>
  void Put(T v) {
    static_assert(std::is_trivially_copyable_v<T>);
    Append(std::string_view(reinterpret_cast<const char*>(&v), sizeof v));
  }
  template <typename T>
  void PutVector(const std::vector<T>& v) {
    static_assert(std::is_trivially_copyable_v<T>);
    Put<uint64_t>(v.size());
    Append(std::string_view(reinterpret_cast<const char*>(v.data()), v.size() * sizeof(T)));
  }
  void PutString(const std::string& s) {
    Put<uint64_t>(s.size());
    Append(s);
  }
  // Bytes as they are, with no length before them.
  void PutBytes(std::string_view bytes) { Append(bytes); }
  // Without a sink: the record. With one: "" once the rest is handed over.
  std::string Take() {
    Flush();
    return std::move(out_);
  }
  // With a sink: hands over what is gathered.
  void Flush() {
    if (sink_ && !out_.empty()) {
      sink_(out_);
      out_.clear();
    }
  }

 private:
  void Append(std::string_view bytes) {
    if (sink_ && out_.size() + bytes.size() > kSinkBlock) {
      Flush();
      if (bytes.size() > kSinkBlock) {
        sink_(bytes);
        return;
      }
    }
    out_.append(bytes);
  }

  Sink sink_;
  std::string out_;
};

class ByteReader {
 public:
  // `what` names the record in errors ("checkpoint: field stop_message is truncated").
  ByteReader(std::string_view in, std::string_view what) : in_(in), what_(what) {}

  template <typename T>
  absl::Status Get(const char* field, T* v) {
    static_assert(std::is_trivially_copyable_v<T>);
    if (in_.size() - at_ < sizeof(T)) return Truncated(field);
    std::memcpy(v, in_.data() + at_, sizeof(T));
    at_ += sizeof(T);
    return absl::OkStatus();
  }
  template <typename T>
  absl::Status GetVector(const char* field, std::vector<T>* v) {
    static_assert(std::is_trivially_copyable_v<T>);
    uint64_t n = 0;
    if (auto st = Get(field, &n); !st.ok()) return st;
    // Refused before any allocation: no field of a record comes near 2^40 elements.
    if (n > (uint64_t{1} << 40) || n * sizeof(T) > in_.size() - at_) return Truncated(field);
    v->resize(n);
    // An empty vector's data() may be null, which memcpy must not get even for 0 bytes.
    if (n > 0) std::memcpy(v->data(), in_.data() + at_, n * sizeof(T));
    at_ += n * sizeof(T);
    return absl::OkStatus();
  }
  absl::Status GetString(const char* field, std::string* s) {
    uint64_t n = 0;
    if (auto st = Get(field, &n); !st.ok()) return st;
    if (n > in_.size() - at_) return Truncated(field);
    s->assign(in_.substr(at_, n));
    at_ += n;
    return absl::OkStatus();
  }
  // OK when every byte was read.
  absl::Status Done() const {
    if (at_ != in_.size()) {
      return absl::InvalidArgumentError(
          absl::StrCat(std::string(what_), ": ", in_.size() - at_, " bytes after the last field"));
    }
    return absl::OkStatus();
  }

 private:
  absl::Status Truncated(const char* field) const {
    return absl::InvalidArgumentError(
        absl::StrCat(std::string(what_), ": field ", field, " is truncated"));
  }
  std::string_view in_;
  std::string_view what_;
  size_t at_ = 0;
};

}  // namespace decima
