// Sends DICOM files to a PACS: by STOW-RS (libcurl, one multipart/related POST of type
// application/dicom) or by C-STORE (DCMTK DcmSCU, one association whose presentation contexts
// are exactly the SOP classes of the files, each offered with the file's own transfer syntax
// and Explicit/Implicit VR Little Endian).
//
// A STOW-RS answer counts as success only when its FailedSOPSequence (0008,1198) has no item:
// Orthanc always includes that attribute, empty, so its presence proves nothing. A C-STORE
// succeeds when every response status is 0x0000 (warnings B000, B007, B006 are reported).
// TCP_NODELAY: DCMTK reads the environment variable (see EnableDcmtkTcpNoDelay).
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "server/dicom/dicom_routes.h"

namespace decima::server {

// Debian's DCMTK leaves Nagle's algorithm on unless TCP_NODELAY=1 is in the environment, which
// made sending the 113-slice CT take 5.3 s instead of 0.08 s. Sets TCP_NODELAY=1 (overriding
// the environment). Call once at start-up before any thread starts (setenv is not thread-safe).
void EnableDcmtkTcpNoDelay();

// Sends `files` to `dest`; returns a one-line summary ("3 instances stored by STOW-RS at URL").
// UNAVAILABLE when the peer cannot be reached or times out; FAILED_PRECONDITION when it refuses
// an instance (the message names the SOP Instance UID and the reason / status); INVALID_ARGUMENT
// for a file that is not DICOM.
absl::StatusOr<std::string> SendDicomFiles(const DicomDestination& dest,
                                           const std::vector<std::filesystem::path>& files);

}  // namespace decima::server
