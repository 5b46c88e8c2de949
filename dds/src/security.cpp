#include "pulsetrack/dds/security.hpp"

#include <dds/dds.h>
#include <dlfcn.h>
#include <fmt/format.h>
#include <openssl/bio.h>
#include <openssl/err.h>
#include <openssl/pem.h>
#include <openssl/pkcs7.h>
#include <openssl/x509.h>
#include <openssl/x509_vfy.h>

#include <cerrno>
#include <cstring>
#include <ctime>
#include <fstream>
#include <iterator>
#include <memory>
#include <system_error>

namespace pulsetrack::dds {

namespace {

using vision::fail;
using vision::Result;

template <auto Free>
struct Deleter {
  template <typename T>
  void operator()(T* p) const {
    Free(p);
  }
};
using X509Ptr = std::unique_ptr<X509, Deleter<X509_free>>;
using KeyPtr = std::unique_ptr<EVP_PKEY, Deleter<EVP_PKEY_free>>;
using BioPtr = std::unique_ptr<BIO, Deleter<BIO_free_all>>;
using StorePtr = std::unique_ptr<X509_STORE, Deleter<X509_STORE_free>>;
using StoreCtxPtr = std::unique_ptr<X509_STORE_CTX, Deleter<X509_STORE_CTX_free>>;
using Pkcs7Ptr = std::unique_ptr<PKCS7, Deleter<PKCS7_free>>;

constexpr size_t kMaxSecurityFileBytes = 1 << 20;

// OpenSSL's last error, for a message.
std::string sslError() {
  const unsigned long e = ERR_get_error();
  ERR_clear_error();
  if (e == 0) return "no detail from OpenSSL";
  char buf[256];
  ERR_error_string_n(e, buf, sizeof buf);
  return buf;
}

Result<std::string> readFile(const std::filesystem::path& path, const char* what) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    return fail(fmt::format("{}: cannot read the {}: {}", path.string(), what,
                            std::generic_category().message(errno)));
  }
  std::string text;
  text.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
  if (text.empty()) return fail(fmt::format("{}: the {} is empty", path.string(), what));
  if (text.size() > kMaxSecurityFileBytes) {
    return fail(fmt::format("{}: the {} is larger than 1 MiB", path.string(), what));
  }
  return text;
}

BioPtr memory(const std::string& text) {
  return BioPtr(BIO_new_mem_buf(text.data(), static_cast<int>(text.size())));
}

std::string timeText(const ASN1_TIME* t) {
  BioPtr out(BIO_new(BIO_s_mem()));
  ASN1_TIME_print(out.get(), t);
  char* data = nullptr;
  const long n = BIO_get_mem_data(out.get(), &data);
  return std::string(data, static_cast<size_t>(n));
}

// A PEM certificate, in its validity period.
Result<X509Ptr> readCertificate(const std::filesystem::path& path, const char* what) {
  auto text = readFile(path, what);
  if (!text) return std::unexpected(text.error());
  BioPtr bio = memory(*text);
  X509Ptr cert(PEM_read_bio_X509(bio.get(), nullptr, nullptr, nullptr));
  if (!cert) {
    return fail(
        fmt::format("{}: the {} is not a PEM certificate ({})", path.string(), what, sslError()));
  }
  if (X509_cmp_current_time(X509_get0_notBefore(cert.get())) > 0) {
    return fail(fmt::format("{}: the {} is not valid before {} (check the clock)", path.string(),
                            what, timeText(X509_get0_notBefore(cert.get()))));
  }
  if (X509_cmp_current_time(X509_get0_notAfter(cert.get())) < 0) {
    return fail(
        fmt::format("{}: the {} expired on {} (scripts/security add-participant makes a "
                    "new one)",
                    path.string(), what, timeText(X509_get0_notAfter(cert.get()))));
  }
  return cert;
}

StorePtr storeOf(X509* ca) {
  StorePtr store(X509_STORE_new());
  X509_STORE_add_cert(store.get(), ca);
  return store;
}

std::string subjectOf(X509* cert) {
  BioPtr out(BIO_new(BIO_s_mem()));
  X509_NAME_print_ex(out.get(), X509_get_subject_name(cert), 0, XN_FLAG_RFC2253);
  char* data = nullptr;
  const long n = BIO_get_mem_data(out.get(), &data);
  return std::string(data, static_cast<size_t>(n));
}

// The signed XML inside an S/MIME document, verified against the permissions CA.
Result<std::string> readSigned(const std::filesystem::path& path, const char* what, X509* ca,
                               const std::filesystem::path& ca_path) {
  auto text = readFile(path, what);
  if (!text) return std::unexpected(text.error());
  BioPtr bio = memory(*text);
  BIO* content = nullptr;
  Pkcs7Ptr p7(SMIME_read_PKCS7(bio.get(), &content));
  BioPtr content_owner(content);
  if (!p7) {
    return fail(fmt::format("{}: the {} is not an S/MIME signed document ({})", path.string(), what,
                            sslError()));
  }
  StorePtr store = storeOf(ca);
  BioPtr out(BIO_new(BIO_s_mem()));
  if (PKCS7_verify(p7.get(), nullptr, store.get(), content, out.get(), PKCS7_TEXT) != 1) {
    return fail(fmt::format("{}: the {} is not signed by the permissions CA {} ({})", path.string(),
                            what, ca_path.string(), sslError()));
  }
  char* data = nullptr;
  const long n = BIO_get_mem_data(out.get(), &data);
  return std::string(data, static_cast<size_t>(n));
}

// The text of the first <tag>...</tag> in xml, or "".
std::string element(const std::string& xml, const std::string& tag) {
  const size_t begin = xml.find("<" + tag + ">");
  if (begin == std::string::npos) return "";
  const size_t start = begin + tag.size() + 2;
  const size_t end = xml.find("</" + tag + ">", start);
  return end == std::string::npos ? "" : xml.substr(start, end - start);
}

// "2027-12-02T12:19:43" as a UTC time; -1 when malformed.
time_t isoTime(const std::string& text) {
  std::tm tm{};
  char tail = 0;
  if (std::sscanf(text.c_str(), "%4d-%2d-%2dT%2d:%2d:%2d%c", &tm.tm_year, &tm.tm_mon, &tm.tm_mday,
                  &tm.tm_hour, &tm.tm_min, &tm.tm_sec, &tail) < 6) {
    return -1;
  }
  tm.tm_year -= 1900;
  tm.tm_mon -= 1;
  return timegm(&tm);
}

}  // namespace

SecurityFiles SecurityFiles::inEnclave(const std::filesystem::path& dir) {
  return {dir / "identity_ca.cert.pem",    dir / "cert.pem",       dir / "key.pem",
          dir / "permissions_ca.cert.pem", dir / "governance.p7s", dir / "permissions.p7s"};
}

Result<std::string> SecurityFiles::check() const {
  auto id_ca = readCertificate(identity_ca, "identity CA certificate");
  if (!id_ca) return std::unexpected(id_ca.error());
  auto cert = readCertificate(certificate, "identity certificate");
  if (!cert) return std::unexpected(cert.error());
  {
    StorePtr store = storeOf(id_ca->get());
    StoreCtxPtr ctx(X509_STORE_CTX_new());
    X509_STORE_CTX_init(ctx.get(), store.get(), cert->get(), nullptr);
    if (X509_verify_cert(ctx.get()) != 1) {
      return fail(
          fmt::format("{}: the identity certificate is not signed by the identity CA {}: {}",
                      certificate.string(), identity_ca.string(),
                      X509_verify_cert_error_string(X509_STORE_CTX_get_error(ctx.get()))));
    }
  }
  auto key_text = readFile(private_key, "private key");
  if (!key_text) return std::unexpected(key_text.error());
  {
    BioPtr bio = memory(*key_text);
    KeyPtr key(PEM_read_bio_PrivateKey(bio.get(), nullptr, nullptr, nullptr));
    if (!key) {
      return fail(fmt::format("{}: not an unencrypted PEM private key ({})", private_key.string(),
                              sslError()));
    }
    if (X509_check_private_key(cert->get(), key.get()) != 1) {
      ERR_clear_error();
      return fail(fmt::format("{}: the private key does not belong to the certificate {}",
                              private_key.string(), certificate.string()));
    }
  }
  auto perm_ca = readCertificate(permissions_ca, "permissions CA certificate");
  if (!perm_ca) return std::unexpected(perm_ca.error());
  auto gov = readSigned(governance, "governance", perm_ca->get(), permissions_ca);
  if (!gov) return std::unexpected(gov.error());
  if (gov->find("<domain_access_rules>") == std::string::npos) {
    return fail(
        fmt::format("{}: the governance has no <domain_access_rules>", governance.string()));
  }
  auto perm = readSigned(permissions, "permissions", perm_ca->get(), permissions_ca);
  if (!perm) return std::unexpected(perm.error());
  const std::string subject = subjectOf(cert->get());
  const std::string granted = element(*perm, "subject_name");
  if (granted != subject) {
    return fail(fmt::format("{}: the permissions are granted to '{}', the certificate {} is '{}'",
                            permissions.string(), granted, certificate.string(), subject));
  }
  const std::string not_after = element(*perm, "not_after");
  const time_t until = isoTime(not_after);
  if (until < 0) {
    return fail(fmt::format("{}: the permissions' <not_after> '{}' is not a date",
                            permissions.string(), not_after));
  }
  if (until < std::time(nullptr)) {
    return fail(
        fmt::format("{}: the permissions expired on {} UTC", permissions.string(), not_after));
  }
  return subject;
}

std::string securityPluginPath(const std::string& plugin) {
  const std::string file = "libdds_security_" + plugin + ".so";
  Dl_info info{};
  if (dladdr(reinterpret_cast<void*>(&dds_create_participant), &info) != 0 &&
      info.dli_fname != nullptr) {
    const std::filesystem::path ddsc = std::filesystem::path(info.dli_fname).parent_path();
    for (const auto& candidate : {ddsc / "libddsc0debian" / file, ddsc / file}) {
      std::error_code ec;
      if (std::filesystem::exists(candidate, ec)) return candidate.string();
    }
  }
  return "dds_security_" + plugin;  // Cyclone's own search (lib<name>.so on the library path)
}

}  // namespace pulsetrack::dds
