// A DICOM peer's raw side for the receiver's tests (tests/server/dicom/dicom_test.cc,
// tests/e2e/dicom_scp_e2e_test.cc): loopback connections from any 127.x address, a hand-made
// A-ASSOCIATE-RQ, a deflate bomb, a process's memory from /proc.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <string>

namespace decima::testing {

// `key` ("VmHWM", "VmRSS") of /proc/PID/status in MiB; -1 if absent.
int64_t ProcessMemoryMb(pid_t pid, const std::string& key);

// A TCP connection to 127.0.0.1:port from `source` (any 127.x address); -1 on failure.
int Connect(int port, const char* source = "127.0.0.1");

// True when the server closed `fd` (EOF or reset, after any PDU it sent) within `within`.
bool ClosedByPeerWithin(int fd, std::chrono::milliseconds within);

// An A-ASSOCIATE-RQ PDU (PS3.8 9.3.2) proposing Verification in implicit VR little endian.
std::string AssociateRequest(const std::string& called, const std::string& calling);

// A connection from `source` whose association (called DECIMA, calling SILENT) was accepted
// and which then sends nothing; -1 unless the receiver answered A-ASSOCIATE-AC within 10 s.
int SilentAssociation(int port, const char* source = "127.0.0.1");

// Writes a Part 10 file in Deflated Explicit VR Little Endian (a CT image's SOP class) whose
// data set holds a private OB element of `zeros` zero bytes after its UIDs: a few hundred KiB
// that inflate to `zeros`. Streams through zlib, so writing it costs no memory.
void WriteDeflateBomb(const std::filesystem::path& path, uint32_t zeros,
                      const std::string& series_uid);

}  // namespace decima::testing
