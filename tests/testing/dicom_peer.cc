#include "tests/testing/dicom_peer.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>
#include <zlib.h>

#include <algorithm>
#include <fstream>
#include <vector>

#include "gtest/gtest.h"

namespace decima::testing {

int64_t ProcessMemoryMb(pid_t pid, const std::string& key) {
  std::ifstream in("/proc/" + std::to_string(pid) + "/status");
  std::string line;
  while (std::getline(in, line)) {
    if (line.rfind(key + ":", 0) == 0) return std::stoll(line.substr(key.size() + 1)) / 1024;
  }
  return -1;
}

int Connect(int port, const char* source) {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return -1;
  sockaddr_in from{};
  from.sin_family = AF_INET;
  ::inet_pton(AF_INET, source, &from.sin_addr);
  sockaddr_in to{};
  to.sin_family = AF_INET;
  to.sin_port = htons(static_cast<uint16_t>(port));
  ::inet_pton(AF_INET, "127.0.0.1", &to.sin_addr);
  if (::bind(fd, reinterpret_cast<sockaddr*>(&from), sizeof(from)) != 0 ||
      ::connect(fd, reinterpret_cast<sockaddr*>(&to), sizeof(to)) != 0) {
    ::close(fd);
    return -1;
  }
  return fd;
}

bool ClosedByPeerWithin(int fd, std::chrono::milliseconds within) {
  const auto end = std::chrono::steady_clock::now() + within;
  char buf[4096];
  for (int i = 0; i < 10000; ++i) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
        end - std::chrono::steady_clock::now());
    if (left.count() <= 0) return false;
    pollfd p{fd, POLLIN, 0};
    if (::poll(&p, 1, static_cast<int>(left.count())) <= 0) continue;
    const ssize_t n = ::recv(fd, buf, sizeof(buf), 0);
    if (n <= 0) return true;
  }
  return false;
}

std::string AssociateRequest(const std::string& called, const std::string& calling) {
  auto item = [](uint8_t type, const std::string& body) {
    std::string s{static_cast<char>(type), '\0', static_cast<char>(body.size() >> 8),
                  static_cast<char>(body.size() & 0xFF)};
    return s + body;
  };
  auto ae = [](std::string t) {
    t.resize(16, ' ');
    return t;
  };
  const std::string pc = item(0x20, std::string("\x01\0\0\0", 4) + item(0x30, "1.2.840.10008.1.1") +
                                        item(0x40, "1.2.840.10008.1.2"));
  const std::string user = item(0x50, item(0x51, std::string("\0\0\x40\0", 4)));
  const std::string body = std::string("\0\x01\0\0", 4) + ae(called) + ae(calling) +
                           std::string(32, '\0') + item(0x10, "1.2.840.10008.3.1.1.1") + pc + user;
  const uint32_t n = static_cast<uint32_t>(body.size());
  return std::string{'\x01',
                     '\0',
                     static_cast<char>(n >> 24),
                     static_cast<char>(n >> 16),
                     static_cast<char>(n >> 8),
                     static_cast<char>(n)} +
         body;
}

int SilentAssociation(int port, const char* source) {
  const int fd = Connect(port, source);
  if (fd < 0) return -1;
  const std::string rq = AssociateRequest("DECIMA", "SILENT");
  unsigned char type = 0;
  pollfd p{fd, POLLIN, 0};
  if (::send(fd, rq.data(), rq.size(), MSG_NOSIGNAL) != static_cast<ssize_t>(rq.size()) ||
      ::poll(&p, 1, 10000) != 1 || ::recv(fd, &type, 1, 0) != 1 || type != 0x02) {
    ::close(fd);
    return -1;
  }
  return fd;
}

void WriteDeflateBomb(const std::filesystem::path& path, uint32_t zeros,
                      const std::string& series_uid) {
  auto le16 = [](uint16_t v) {
    return std::string{static_cast<char>(v), static_cast<char>(v >> 8)};
  };
  auto le32 = [&](uint32_t v) {
    return le16(static_cast<uint16_t>(v)) + le16(static_cast<uint16_t>(v >> 16));
  };
  auto tag = [&](uint16_t g, uint16_t e) { return le16(g) + le16(e); };
  auto short_el = [&](uint16_t g, uint16_t e, const char* vr, std::string v) {
    if (v.size() % 2) v.push_back(vr[0] == 'U' && vr[1] == 'I' ? '\0' : ' ');
    return tag(g, e) + vr + le16(static_cast<uint16_t>(v.size())) + v;
  };
  const std::string sop_class = "1.2.840.10008.5.1.4.1.1.2",
                    sop = "1.2.826.0.1.3680043.9.7777.99.1";
  std::string meta = short_el(0x0002, 0x0001, "OB", "");
  meta = tag(0x0002, 0x0001) + "OB" + std::string(2, '\0') + le32(2) + std::string("\0\x01", 2);
  meta += short_el(0x0002, 0x0002, "UI", sop_class) + short_el(0x0002, 0x0003, "UI", sop) +
          short_el(0x0002, 0x0010, "UI", "1.2.840.10008.1.2.1.99");
  std::ofstream out(path, std::ios::binary);
  out << std::string(128, '\0') << "DICM" << tag(0x0002, 0x0000) << "UL" << le16(4)
      << le32(static_cast<uint32_t>(meta.size())) << meta;
  // The private element comes after the UIDs, as a vendor's large private block does.
  const std::string head =
      short_el(0x0008, 0x0016, "UI", sop_class) + short_el(0x0008, 0x0018, "UI", sop) +
      short_el(0x0020, 0x000E, "UI", series_uid) + short_el(0x0029, 0x0010, "LO", "DECIMA TEST") +
      tag(0x0029, 0x1001) + "OB" + std::string(2, '\0') + le32(zeros);
  z_stream z{};
  ASSERT_EQ(deflateInit2(&z, 9, Z_DEFLATED, -15, 9, Z_DEFAULT_STRATEGY), Z_OK);  // raw deflate
  std::vector<unsigned char> in(1 << 20, 0), buf(1 << 16);
  auto pump = [&](const unsigned char* data, size_t n, int flush) {
    z.next_in = const_cast<unsigned char*>(data);
    z.avail_in = static_cast<uInt>(n);
    do {
      z.next_out = buf.data();
      z.avail_out = static_cast<uInt>(buf.size());
      deflate(&z, flush);
      out.write(reinterpret_cast<const char*>(buf.data()),
                static_cast<std::streamsize>(buf.size() - z.avail_out));
    } while (z.avail_out == 0);
  };
  pump(reinterpret_cast<const unsigned char*>(head.data()), head.size(), Z_NO_FLUSH);
  for (uint32_t left = zeros; left > 0;) {
    const uint32_t n = std::min<uint32_t>(left, static_cast<uint32_t>(in.size()));
    pump(in.data(), n, Z_NO_FLUSH);
    left -= n;
  }
  pump(nullptr, 0, Z_FINISH);
  deflateEnd(&z);
}

}  // namespace decima::testing
