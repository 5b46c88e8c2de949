#pragma once
// DDS Security (OMG DDS Security 1.1 through Cyclone DDS's standard plugins): the six files of a
// participant, as ROS 2's SROS2 lays them out in an enclave folder, and their checks. The files
// are made by scripts/security; docs/security.md gives the policy.

#include <filesystem>
#include <string>

#include "pulsetrack/vision/error.hpp"

namespace pulsetrack::dds {

struct SecurityFiles {
  std::filesystem::path identity_ca;     // identity_ca.cert.pem: the CA that signs identities
  std::filesystem::path certificate;     // cert.pem: this participant's identity
  std::filesystem::path private_key;     // key.pem: its key (unencrypted PEM)
  std::filesystem::path permissions_ca;  // permissions_ca.cert.pem: signs governance/permissions
  std::filesystem::path governance;      // governance.p7s: the domain's rules (S/MIME signed)
  std::filesystem::path permissions;     // permissions.p7s: what this participant may do

  // The files of an SROS2 enclave folder (KEYSTORE/enclaves/<name>).
  static SecurityFiles inEnclave(const std::filesystem::path& dir);

  // Checks with OpenSSL what Cyclone DDS would refuse with a bare "not allowed by security":
  // every file readable and well-formed; the certificate signed by the identity CA, neither
  // expired nor not yet valid, and the key its own; governance and permissions signed by the
  // permissions CA; the permissions granted to this certificate's subject and not expired.
  // Errors name the file. Returns the certificate's subject ("CN=/pulsetrack/daemon").
  [[nodiscard]] vision::Result<std::string> check() const;
};

// The file Cyclone DDS loads a security plugin from ("auth", "ac" or "crypto"): Debian installs
// them beside libddsc in libddsc0debian/, where Cyclone's default search does not look.
std::string securityPluginPath(const std::string& plugin);

}  // namespace pulsetrack::dds
