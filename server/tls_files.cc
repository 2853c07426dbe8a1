#include "server/tls_files.h"

#include <openssl/bio.h>
#include <openssl/err.h>
#include <openssl/pem.h>
#include <openssl/x509.h>

#include <memory>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"

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

// The first certificate of a PEM file, checked for its validity period.
absl::StatusOr<std::unique_ptr<X509, X509Free>> ReadCertificate(const char* flag,
                                                                const std::string& file) {
  std::unique_ptr<BIO, BioFree> bio(BIO_new_file(file.c_str(), "r"));
  if (!bio) return Bad(flag, file, "cannot open");
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

}  // namespace

absl::Status CheckTlsFiles(const std::string& cert, const std::string& key,
                           const std::string& client_ca) {
  auto x = ReadCertificate("--tls-cert", cert);
  if (!x.ok()) return x.status();
  std::unique_ptr<BIO, BioFree> bio(BIO_new_file(key.c_str(), "r"));
  if (!bio) return Bad("--tls-key", key, "cannot open");
  std::unique_ptr<EVP_PKEY, KeyFree> k(
      PEM_read_bio_PrivateKey(bio.get(), nullptr, nullptr, nullptr));
  if (!k) return Bad("--tls-key", key, "not a PEM private key (" + OpenSslError() + ")");
  if (X509_check_private_key(x->get(), k.get()) != 1) {
    ERR_clear_error();
    return Bad("--tls-key", key, absl::StrCat("does not belong to the certificate in ", cert));
  }
  if (!client_ca.empty()) {
    auto ca = ReadCertificate("--tls-client-ca", client_ca);
    if (!ca.ok()) return ca.status();
  }
  return absl::OkStatus();
}

}  // namespace decima::server
