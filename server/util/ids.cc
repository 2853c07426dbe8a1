#include "server/util/ids.h"

#include <cstdint>
#include <random>

namespace decima::server {

std::string NewId() {
  thread_local std::mt19937_64 rng([] {
    std::random_device rd;
    std::seed_seq seq{rd(), rd(), rd(), rd()};
    return std::mt19937_64(seq);
  }());
  static const char kHex[] = "0123456789abcdef";
  const uint64_t v = rng();
  std::string id(16, '0');
  for (int i = 0; i < 16; ++i) id[i] = kHex[(v >> (4 * i)) & 15];
  return id;
}

}  // namespace decima::server
