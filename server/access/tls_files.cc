#include "server/access/tls_files.h"

#include <openssl/bio.h>
#include <openssl/err.h>
#include <openssl/pem.h>
#include <openssl/x509.h>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>
#include <sstream>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "spdlog/spdlog.h"

namespace decima::server {
namespace {

std::string OpenSslError() {
  unsigned long e = ERR_get_error();
  ERR_clear_error();
  if (e == 0) return "no PEM data";
  char buf[256];
  ERR_error_string_n(e, buf, sizeof buf);
  return buf;
}

struct BioFree {
  void operator()(BIO* b) const { BIO_free(b); }
};
struct X509Free {
  void operator()(X509* x) const { X509_free(x); }
};
struct KeyFree {
  void operator()(EVP_PKEY* k) const { EVP_PKEY_free(k); }
};

absl::Status Bad(const char* flag, const std::string& file, const std::string& what) {
  return absl::InvalidArgumentError(absl::StrCat(flag, " ", file, ": ", what));
}

// The first certificate of PEM text, checked for its validity period.
absl::StatusOr<std::unique_ptr<X509, X509Free>> ReadCertificate(const char* flag,
                                                                const std::string& file,
                                                                const std::string& pem) {
  std::unique_ptr<BIO, BioFree> bio(BIO_new_mem_buf(pem.data(), static_cast<int>(pem.size())));
  if (!bio) return Bad(flag, file, "out of memory");
  std::unique_ptr<X509, X509Free> x(PEM_read_bio_X509(bio.get(), nullptr, nullptr, nullptr));
  if (!x) return Bad(flag, file, "not a PEM certificate (" + OpenSslError() + ")");
  if (X509_cmp_current_time(X509_get0_notAfter(x.get())) < 0) {
    return Bad(flag, file, "the certificate has expired");
  }
  if (X509_cmp_current_time(X509_get0_notBefore(x.get())) > 0) {
    return Bad(flag, file, "the certificate is not valid yet");
  }
  return x;
}

// The whole file, or INVALID_ARGUMENT naming it. At most 1 MiB: a PEM chain is kilobytes.
absl::StatusOr<std::string> ReadPem(const char* flag, const std::string& file) {
  std::ifstream in(file, std::ios::binary);
  if (!in) return Bad(flag, file, absl::StrCat("cannot open (", std::strerror(errno), ")"));
  std::string out(1 << 20, '\0');
  in.read(out.data(), static_cast<std::streamsize>(out.size()));
  if (in.gcount() == static_cast<std::streamsize>(out.size())) {
    return Bad(flag, file, "larger than 1 MiB; expected a PEM file");
  }
  out.resize(static_cast<size_t>(in.gcount()));
  return out;
}

// Writes `text` to `path` through a temporary file and a rename, readable by the owner only.
absl::Status WriteAtomically(const std::string& path, const std::string& text) {
  const std::string tmp = path + ".tmp";
  int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC | O_NOFOLLOW, 0600);
  if (fd < 0) return absl::InternalError(absl::StrCat(tmp, ": ", std::strerror(errno)));
  const bool ok = ::write(fd, text.data(), text.size()) == static_cast<ssize_t>(text.size());
  ::close(fd);
  if (!ok || ::rename(tmp.c_str(), path.c_str()) != 0) {
    return absl::InternalError(absl::StrCat(path, ": ", std::strerror(errno)));
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status CheckTlsPem(const std::string& cert_pem, const std::string& key_pem,
                         const std::string& client_ca_pem, const std::string& cert_file,
                         const std::string& key_file, const std::string& client_ca_file) {
  auto x = ReadCertificate("--tls-cert", cert_file, cert_pem);
  if (!x.ok()) return x.status();
  std::unique_ptr<BIO, BioFree> bio(
      BIO_new_mem_buf(key_pem.data(), static_cast<int>(key_pem.size())));
  if (!bio) return Bad("--tls-key", key_file, "out of memory");
  std::unique_ptr<EVP_PKEY, KeyFree> k(
      PEM_read_bio_PrivateKey(bio.get(), nullptr, nullptr, nullptr));
  if (!k) return Bad("--tls-key", key_file, "not a PEM private key (" + OpenSslError() + ")");
  if (X509_check_private_key(x->get(), k.get()) != 1) {
    ERR_clear_error();
    return Bad("--tls-key", key_file,
               absl::StrCat("does not belong to the certificate in ", cert_file));
  }
  if (!client_ca_file.empty()) {
    auto ca = ReadCertificate("--tls-client-ca", client_ca_file, client_ca_pem);
    if (!ca.ok()) return ca.status();
  }
  return absl::OkStatus();
}

absl::Status CheckTlsFiles(const std::string& cert, const std::string& key,
                           const std::string& client_ca) {
  auto c = ReadPem("--tls-cert", cert);
  if (!c.ok()) return c.status();
  auto k = ReadPem("--tls-key", key);
  if (!k.ok()) return k.status();
  std::string ca;
  if (!client_ca.empty()) {
    auto a = ReadPem("--tls-client-ca", client_ca);
    if (!a.ok()) return a.status();
    ca = std::move(*a);
  }
  return CheckTlsPem(*c, *k, ca, cert, key, client_ca);
}

absl::StatusOr<std::unique_ptr<TlsFileGuard>> TlsFileGuard::Start(
    const std::string& cert, const std::string& key, const std::string& client_ca,
    std::chrono::milliseconds period) {
  if (auto st = CheckTlsFiles(cert, key, client_ca); !st.ok()) return st;
  std::unique_ptr<TlsFileGuard> g(new TlsFileGuard());
  g->cert_ = cert;
  g->key_ = key;
  g->client_ca_ = client_ca;
  const char* tmpdir = std::getenv("TMPDIR");
  std::string tmpl = absl::StrCat(tmpdir && *tmpdir ? tmpdir : "/tmp", "/decima-tls-XXXXXX");
  if (::mkdtemp(tmpl.data()) == nullptr) {
    return absl::InternalError(
        absl::StrCat("TLS: cannot make a private folder ", tmpl, ": ", std::strerror(errno)));
  }
  g->dir_ = tmpl;
  g->Reload();
  if (g->served_.empty()) {
    return absl::InternalError(absl::StrCat("TLS: cannot copy the files into ", g->dir_));
  }
  g->task_ = std::make_unique<PeriodicTask>(period, [p = g.get()] { p->Reload(); });
  return g;
}

TlsFileGuard::~TlsFileGuard() {
  if (task_) task_->Stop();
  std::error_code ec;
  if (!dir_.empty()) std::filesystem::remove_all(dir_, ec);
}

void TlsFileGuard::Reload() {
  auto c = ReadPem("--tls-cert", cert_);
  auto k = ReadPem("--tls-key", key_);
  absl::StatusOr<std::string> ca = std::string();
  if (!client_ca_.empty()) ca = ReadPem("--tls-client-ca", client_ca_);
  absl::Status st = !c.ok() ? c.status() : !k.ok() ? k.status() : ca.status();
  const std::string all =
      st.ok() ? absl::StrCat(c->size(), ":", *c, k->size(), ":", *k, ca->size(), ":", *ca) : "";
  if (st.ok() && all == served_) return;  // unchanged
  if (st.ok()) st = CheckTlsPem(*c, *k, *ca, cert_, key_, client_ca_);
  if (!st.ok()) {
    // Logged once per broken content (an unreadable file each time it is seen anew).
    const std::string seen = all.empty() ? std::string(st.message()) : all;
    if (seen != refused_) {
      spdlog::error("TLS reload refused, the last good certificate keeps serving: {}",
                    std::string(st.message()));
      refused_ = seen;
    }
    return;
  }
  // Key first: gRPC re-reads the pair when a file's time changed during its read.
  for (auto [path, text] : {std::pair{served_key(), &*k}, std::pair{served_cert(), &*c},
                            std::pair{served_client_ca(), &*ca}}) {
    if (path.empty()) continue;
    if (absl::Status w = WriteAtomically(path, *text); !w.ok()) {
      spdlog::error("TLS reload: {}", std::string(w.message()));
      return;
    }
  }
  if (!served_.empty()) spdlog::info("TLS files changed and checked: new handshakes use them");
  served_ = all;
  refused_.clear();
}

}  // namespace decima::server
