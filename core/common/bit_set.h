// A fixed-size set of flags, one bit per element: 1/8 of a byte array's memory, so large flag
// arrays (cells, voxels) stay in cache. Test/Set are not thread-safe for concurrent writes to one
// word; TestShared/SetShared are, for threads that each own different bits of shared words.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <vector>

namespace decima {

class BitSet {
 public:
  BitSet() = default;
  explicit BitSet(int64_t n) : words_((n + 63) / 64, 0) {}
  bool Test(int64_t i) const { return (words_[i >> 6] >> (i & 63)) & 1; }
  void Set(int64_t i) { words_[i >> 6] |= uint64_t{1} << (i & 63); }
  bool TestShared(int64_t i) const {
    return (std::atomic_ref<uint64_t>(const_cast<uint64_t&>(words_[i >> 6]))
                .load(std::memory_order_relaxed) >>
            (i & 63)) &
           1;
  }
  void SetShared(int64_t i) {
    std::atomic_ref<uint64_t>(words_[i >> 6])
        .fetch_or(uint64_t{1} << (i & 63), std::memory_order_relaxed);
  }
  void ClearAll() { std::fill(words_.begin(), words_.end(), 0); }

 private:
  std::vector<uint64_t> words_;
};

}  // namespace decima
