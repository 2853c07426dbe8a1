// The PACS side's configuration (--dicom-routes FILE, JSON): which job spec a received series
// runs with and where its results go, chosen by the calling and called AE titles of the
// association that brought it.
//
//   {
//     "refuse_unknown_calling_ae": true,        // default false: unknown callers use "default"
//     "routes": [
//       {"name": "ct-head",
//        "calling_ae": "ORTHANC",               // "" or "*": any; compared exactly otherwise
//        "called_ae": "DECIMA",                 // "" or "*": any
//        "spec": {"regions": 3, "targetReduction": 0.5, "imageSize": 128},  // decima.v1.JobSpec
//                                               // as proto JSON, without "volume"
//        "destination": {                       // optional: where SEG + SC are sent
//          "stow_url": "https://pacs/dicom-web/studies",  // STOW-RS, or:
//          "dicom": "127.0.0.1:4242", "aet": "ORTHANC",    // C-STORE
//          "username": "u", "password": "p",   // HTTP basic auth, or
//          "bearer_token": "t",                // HTTP bearer auth
//          "ca_file": "/etc/ssl/pacs.pem",     // TLS trust (default: the system's)
//          "timeout_seconds": 60}}
//     ]
//   }
// The first route matching both AE titles wins. Without a file, every caller gets the default
// route: the default JobSpec and no destination. Whatever the route, the volume and job of a
// received series are created by the principal "dicom:<calling AE title>" (not per route: the
// sender is what the AE title identifies), so a tokens-file submitter of that name sees them.
#pragma once

#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "decima/v1/jobs.pb.h"

namespace decima::server {

struct DicomDestination {
  std::string stow_url;  // STOW-RS endpoint (POST .../studies)
  std::string host;      // C-STORE peer, when stow_url is empty
  int port = 0;
  std::string aet;          // the peer's AE title
  std::string calling_aet;  // ours (set from --dicom-aet)
  std::string username, password, bearer_token, ca_file;
  int timeout_seconds = 60;
  bool configured() const { return !stow_url.empty() || !host.empty(); }
};

struct DicomRoute {
  std::string name;
  std::string calling_ae, called_ae;  // "" = any
  v1::JobSpec spec;                   // volume unset
  DicomDestination destination;
};

struct DicomRoutes {
  bool refuse_unknown_calling_ae = false;
  std::vector<DicomRoute> routes;

  // The first route matching both titles; the built-in default route (name "default", default
  // spec, no destination) when none matches and unknown callers are accepted; nullptr when
  // they are refused.
  const DicomRoute* Match(const std::string& calling_ae, const std::string& called_ae) const;
  const DicomRoute* Find(const std::string& name) const;

 private:
  DicomRoute default_route_{"default", "", "", {}, {}};
};

// Parses the routes file. INVALID_ARGUMENT naming the file and the field ("routes[1].spec: ...")
// for malformed JSON, an unknown key, a spec that does not parse or validate, a destination
// with neither or both of stow_url and dicom, or a bad host:port.
absl::StatusOr<DicomRoutes> LoadDicomRoutes(const std::string& path);
absl::StatusOr<DicomRoutes> ParseDicomRoutes(const std::string& json_text,
                                             const std::string& source_name);

}  // namespace decima::server
