// The framing between server and job child: whole messages out in order however the bytes are
// split by the pipe, and a broken stream is an error, not a hang or a crash.
#include "server/jobs/worker_protocol.h"

#include <fcntl.h>
#include <unistd.h>

#include <gtest/gtest.h>

namespace decima::server {
namespace {

std::string Frames(const std::vector<worker::WorkerMessage>& messages) {
  int p[2];
  EXPECT_EQ(::pipe(p), 0);
  for (const auto& m : messages) EXPECT_TRUE(WriteFrame(p[1], m).ok());
  ::close(p[1]);
  std::string bytes;
  char buf[4096];
  ssize_t n;
  while ((n = ::read(p[0], buf, sizeof buf)) > 0) bytes.append(buf, static_cast<size_t>(n));
  ::close(p[0]);
  return bytes;
}

std::vector<worker::WorkerMessage> Sample() {
  std::vector<worker::WorkerMessage> out(3);
  out[0].mutable_progress()->set_stage("segment");
  out[0].mutable_progress()->set_fraction(0.5);
  (*out[0].mutable_progress()->mutable_metrics())["iteration"] = 7;
  out[1].mutable_progress()->set_message(std::string(300, 'x'));  // a multi-byte varint size
  auto* a = out[2].mutable_result()->add_artifacts();
  a->set_name("mesh.vtu");
  out[2].mutable_result()->set_metrics_json("{}");
  return out;
}

TEST(FrameReader, YieldsEveryMessageWhateverTheReadBoundaries) {
  const std::string bytes = Frames(Sample());
  for (size_t chunk : {size_t{1}, size_t{2}, size_t{7}, bytes.size()}) {
    FrameReader reader;
    std::vector<worker::WorkerMessage> got;
    for (size_t i = 0; i < bytes.size(); i += chunk) {
      reader.Append(bytes.data() + i, std::min(chunk, bytes.size() - i));
      worker::WorkerMessage m;
      while (reader.Next(&m)) got.push_back(m);
    }
    ASSERT_EQ(got.size(), 3u) << "chunk " << chunk;
    EXPECT_EQ(got[0].progress().stage(), "segment");
    EXPECT_EQ(got[0].progress().metrics().at("iteration"), 7);
    EXPECT_EQ(got[1].progress().message().size(), 300u);
    EXPECT_EQ(got[2].result().artifacts(0).name(), "mesh.vtu");
    EXPECT_TRUE(reader.status().ok());
    EXPECT_EQ(reader.pending(), 0u);
  }
}

TEST(FrameReader, ATruncatedLastMessageStaysPending) {
  const std::string bytes = Frames(Sample());
  FrameReader reader;
  reader.Append(bytes.data(), bytes.size() - 3);
  worker::WorkerMessage m;
  int n = 0;
  while (reader.Next(&m)) ++n;
  EXPECT_EQ(n, 2);
  EXPECT_GT(reader.pending(), 0u) << "the runner reports this as a cut-off message";
}

TEST(FrameReader, AnOversizedFrameIsAnErrorAndStopsTheStream) {
  FrameReader reader;
  // varint 2^40: far above kMaxFrameBytes.
  const char huge[] = {'\x80', '\x80', '\x80', '\x80', '\x80', '\x20'};
  reader.Append(huge, sizeof huge);
  worker::WorkerMessage m;
  EXPECT_FALSE(reader.Next(&m));
  EXPECT_EQ(reader.status().code(), absl::StatusCode::kDataLoss);
  const std::string ok = Frames(Sample());
  reader.Append(ok.data(), ok.size());
  EXPECT_FALSE(reader.Next(&m)) << "nothing after a broken frame is trusted";
}

TEST(FrameReader, BytesThatDoNotParseAreAnError) {
  FrameReader reader;
  const char bad[] = {'\x03', '\xff', '\xff', '\xff'};
  reader.Append(bad, sizeof bad);
  worker::WorkerMessage m;
  EXPECT_FALSE(reader.Next(&m));
  EXPECT_FALSE(reader.status().ok());
}

}  // namespace
}  // namespace decima::server
