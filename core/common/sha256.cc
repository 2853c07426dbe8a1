#include "core/common/sha256.h"

#include <openssl/evp.h>

#include <algorithm>
#include <cstdio>
#include <vector>

#include "absl/strings/str_cat.h"

namespace decima {

struct Sha256::Impl {
  EVP_MD_CTX* ctx = nullptr;
};

Sha256::Sha256() : impl_(std::make_unique<Impl>()) {
  impl_->ctx = EVP_MD_CTX_new();
  EVP_DigestInit_ex(impl_->ctx, EVP_sha256(), nullptr);
}

Sha256::~Sha256() { EVP_MD_CTX_free(impl_->ctx); }

void Sha256::Update(const void* data, size_t size) { EVP_DigestUpdate(impl_->ctx, data, size); }

std::string Sha256::HexDigest() {
  unsigned char md[EVP_MAX_MD_SIZE];
  unsigned int len = 0;
  EVP_DigestFinal_ex(impl_->ctx, md, &len);
  static const char kHex[] = "0123456789abcdef";
  std::string out;
  out.reserve(2 * len);
  for (unsigned int i = 0; i < len; ++i) {
    out.push_back(kHex[md[i] >> 4]);
    out.push_back(kHex[md[i] & 15]);
  }
  return out;
}

absl::Status HashFilePrefix(const std::filesystem::path& path, int64_t limit, Sha256& hash,
                            int64_t* hashed) {
  std::FILE* f = std::fopen(path.c_str(), "rb");
  if (f == nullptr) return absl::NotFoundError(absl::StrCat(path.string(), ": cannot open"));
  std::vector<char> buf(1 << 20);
  int64_t left = limit < 0 ? INT64_MAX : limit;
  int64_t total = 0;
  while (left > 0) {
    size_t want = static_cast<size_t>(std::min<int64_t>(left, static_cast<int64_t>(buf.size())));
    size_t got = std::fread(buf.data(), 1, want, f);
    if (got == 0) break;
    hash.Update(buf.data(), got);
    left -= static_cast<int64_t>(got);
    total += static_cast<int64_t>(got);
  }
  bool err = std::ferror(f) != 0;
  std::fclose(f);
  if (hashed != nullptr) *hashed = total;
  if (err) return absl::DataLossError(absl::StrCat(path.string(), ": read error"));
  if (limit >= 0 && left > 0) {
    return absl::DataLossError(absl::StrCat(path.string(), ": shorter than ", limit, " bytes"));
  }
  return absl::OkStatus();
}

}  // namespace decima
