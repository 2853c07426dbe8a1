// decima-service-bench: the service figures of issue 6, printed as one JSON object.
//   submit_to_running_ms: CreateJob -> RUNNING event at the client, idle server (p50, p90)
//   upload_mb_per_s:      one 256 MB blob over loopback (median of 3; fsync on and off)
//   watchers:             job time (start -> end, server clock) with 0 and 100 watchers
//   job_overhead:         (job time - the pipeline's own total in metrics.json) / pipeline total
// Usage: decima-service-bench [--volume FILE] [--jobs N]
//        decima-service-bench --create-volume FILE [--repeat N]
//        decima-service-bench --security 1 [--jobs N]
//   the second form only measures CreateVolume (p50, p90 ms) of FILE, uploaded once; the third
//   the cost of TLS (issue 16): submit -> RUNNING (p50, p90) and the 256 MB upload (median of
//   3, fsync on) over plaintext, TLS and mutual TLS, with certificates made by `openssl`.
#include <google/protobuf/util/time_util.h>
#include <grpcpp/grpcpp.h>
#include <signal.h>

#include <algorithm>
#include <atomic>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <random>
#include <thread>

#include "client/client_lib.h"
#include "tests/e2e/e2e_util.h"

namespace fs = std::filesystem;
using namespace decima;
using namespace std::chrono_literals;
using google::protobuf::util::TimeUtil;

namespace {

double Percentile(std::vector<double> v, double p) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  return v[static_cast<size_t>(p * (v.size() - 1) + 0.5)];
}

double Median(std::vector<double> v) { return Percentile(std::move(v), 0.5); }

std::string MakeVolume(const client::Connection& c, const fs::path& file) {
  std::vector<client::InputFile> files;
  std::string err;
  client::CollectInputs(file, &files, &err);
  client::HashInputs(&files, &err);
  client::UploadBlob(c, files[0], nullptr, 3, nullptr);
  v1::CreateVolumeRequest req;
  auto* f = req.mutable_volume()->add_files();
  f->set_path(files[0].name);
  f->set_blob("blobs/" + files[0].sha256);
  v1::Volume vol;
  grpc::Status s = v1::Volumes::NewStub(c.channel)->CreateVolume(c.Context().get(), req, &vol);
  if (!s.ok()) std::fprintf(stderr, "create volume: %s\n", s.error_message().c_str());
  return vol.name();
}

// Creates a job and waits on a watch stream until it reaches `until_state` (RUNNING or final);
// returns seconds from before CreateJob to that event, and the final job in *job.
double SubmitAndWait(const client::Connection& c, const std::string& volume, bool until_final,
                     v1::Job* job) {
  auto stub = v1::Jobs::NewStub(c.channel);
  v1::CreateJobRequest req;
  req.mutable_spec()->set_volume(volume);
  req.mutable_spec()->set_image_size(128);
  auto t0 = std::chrono::steady_clock::now();
  stub->CreateJob(c.Context().get(), req, job);
  double t_running = -1;
  v1::WatchJobRequest w;
  w.set_name(job->name());
  auto ctx = c.Context(false);
  auto reader = stub->WatchJob(ctx.get(), w);
  v1::JobEvent ev;
  while (reader->Read(&ev)) {
    if (ev.has_state_change() && ev.state_change().state() == v1::RUNNING && t_running < 0) {
      t_running = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      if (!until_final) ctx->TryCancel();
    }
  }
  reader->Finish();
  v1::GetJobRequest g;
  g.set_name(job->name());
  // Wait for the job to end so the next one starts on an idle server.
  for (;;) {
    stub->GetJob(c.Context().get(), g, job);
    if (job->state() >= v1::SUCCEEDED) break;
    std::this_thread::sleep_for(10ms);
  }
  return t_running;
}

double JobSeconds(const v1::Job& j) {
  return TimeUtil::DurationToNanoseconds(j.end_time() - j.start_time()) / 1e9;
}

// The pipeline's own seconds (metrics.json "seconds.total"), 0 when absent.
double PipelineSeconds(const v1::Job& j) {
  auto m = nlohmann::json::parse(j.metrics_json(), nullptr, false);
  if (!m.is_object() || !m.contains("seconds")) return 0;
  return m["seconds"].value("total", 0.0);
}

// CreateVolume latency of one uploaded file: the header check and the manifest, no upload.
int MeasureCreateVolume(const fs::path& scratch, const fs::path& file, int repeat) {
  e2e::ServerProcess server(scratch / "data-cv", {"--workers", "1"});
  std::string err;
  auto c = client::Connect(server.address(), "", {}, 60s, &err);
  std::vector<client::InputFile> files;
  client::CollectInputs(file, &files, &err);
  client::HashInputs(&files, &err);
  for (const auto& f : files) client::UploadBlob(c, f, nullptr, 3, nullptr);
  v1::CreateVolumeRequest req;
  for (const auto& f : files) {
    auto* mf = req.mutable_volume()->add_files();
    mf->set_path(f.name);
    mf->set_blob("blobs/" + f.sha256);
  }
  auto stub = v1::Volumes::NewStub(c.channel);
  std::vector<double> ms;
  for (int i = 0; i < repeat; ++i) {
    v1::Volume vol;
    auto t0 = std::chrono::steady_clock::now();
    grpc::Status s = stub->CreateVolume(c.Context().get(), req, &vol);
    ms.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count() *
                 1000);
    if (!s.ok()) {
      std::fprintf(stderr, "create volume: %s\n", s.error_message().c_str());
      return 1;
    }
  }
  nlohmann::json out;
  out["volume"] = file.string();
  out["create_volume_ms"] = {{"p50", Median(ms)}, {"p90", Percentile(ms, 0.9)}, {"n", repeat}};
  std::printf("%s\n", out.dump(2).c_str());
  return 0;
}

// Seconds to upload a fresh 256 MB random blob (seeded by `seed`), -1 on failure.
double UploadSeconds(const client::Connection& c, const fs::path& scratch, int seed) {
  fs::path blob = scratch / "blob.bin";
  {
    std::mt19937_64 rng(seed);
    std::vector<uint64_t> buf(1 << 17);
    std::ofstream f(blob, std::ios::binary | std::ios::trunc);
    for (int m = 0; m < 256; ++m) {
      for (auto& x : buf) x = rng();
      f.write(reinterpret_cast<const char*>(buf.data()), 1 << 20);
    }
  }
  std::vector<client::InputFile> files;
  std::string err;
  client::CollectInputs(blob, &files, &err);
  client::HashInputs(&files, &err);
  auto t0 = std::chrono::steady_clock::now();
  grpc::Status s = client::UploadBlob(c, files[0], nullptr, 1, nullptr);
  double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  fs::remove(blob);
  if (!s.ok()) {
    std::fprintf(stderr, "upload: %s\n", s.error_message().c_str());
    return -1;
  }
  return secs;
}

// Plaintext, TLS and mutual TLS side by side, on the same machine in one run.
int MeasureSecurity(const fs::path& scratch, const fs::path& volume, int jobs) {
  e2e::TestPki pki;
  if (std::string err = e2e::MakeTestPki(scratch / "pki", {"bench"}, &pki); !err.empty()) {
    std::fprintf(stderr, "certificates: %s\n", err.c_str());
    return 1;
  }
  nlohmann::json out;
  out["volume"] = volume.string();
  int n = 0;
  for (const char* mode : {"plaintext", "tls", "mtls"}) {
    std::vector<std::string> flags = {"--workers", "1", "--max-upload-mb", "1024"};
    client::TlsFiles tls;
    if (std::string(mode) != "plaintext") {
      flags.insert(flags.end(), {"--tls-cert", pki.server_cert().string(), "--tls-key",
                                 pki.server_key().string()});
      tls.ca_file = pki.ca().string();
    }
    if (std::string(mode) == "mtls") {
      flags.insert(flags.end(), {"--tls-client-ca", pki.ca().string()});
      tls.cert_file = pki.cert("bench").string();
      tls.key_file = pki.key("bench").string();
    }
    e2e::ServerProcess server(scratch / ("data-" + std::string(mode)), flags);
    std::string err;
    auto c = client::Connect(server.address(), "", tls, 60s, &err);
    if (!c.channel) {
      std::fprintf(stderr, "%s\n", err.c_str());
      return 1;
    }
    std::string vol = MakeVolume(c, volume);
    std::vector<double> lat;
    for (int i = 0; i < jobs; ++i) {
      v1::Job j;
      lat.push_back(SubmitAndWait(c, vol, false, &j) * 1000);
    }
    std::vector<double> rates;
    for (int rep = 0; rep < 3; ++rep) {
      double secs = UploadSeconds(c, scratch, 1000 * ++n + rep);
      if (secs <= 0) return 1;
      rates.push_back(256 * 1048576 / 1e6 / secs);
    }
    out[mode] = {{"submit_to_running_ms",
                  {{"p50", Median(lat)}, {"p90", Percentile(lat, 0.9)}, {"n", jobs}}},
                 {"upload_mb_per_s_fsync", {{"median", Median(rates)}, {"runs", rates}}}};
  }
  std::printf("%s\n", out.dump(2).c_str());
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  fs::path volume, create_volume;
  int jobs = 20, repeat = 15;
  bool security = false;
  constexpr char kUsage[] =
      "usage: decima-service-bench [--volume FILE] [--jobs N]\n"
      "       decima-service-bench --create-volume FILE [--repeat N]\n"
      "       decima-service-bench --security 1 [--jobs N]\n"
      "Prints one JSON object: submit -> RUNNING latency, upload MB/s, watcher cost and job\n"
      "overhead; --create-volume: CreateVolume latency of FILE; --security: the same over\n"
      "plaintext, TLS and mutual TLS.\n";
  for (int i = 1; i < argc; i += 2) {
    const std::string k = argv[i];
    if (k == "--help" || k == "-h") {
      std::fputs(kUsage, stdout);
      return 0;
    }
    const bool known = k == "--volume" || k == "--jobs" || k == "--create-volume" ||
                       k == "--repeat" || k == "--security";
    if (!known || i + 1 >= argc) {
      std::fprintf(stderr, "decima-service-bench: %s %s\n%s", k.c_str(),
                   known ? "needs a value" : "is not an option", kUsage);
      return 2;
    }
    if (k == "--volume") volume = argv[i + 1];
    if (k == "--jobs") jobs = std::atoi(argv[i + 1]);
    if (k == "--create-volume") create_volume = argv[i + 1];
    if (k == "--repeat") repeat = std::atoi(argv[i + 1]);
    if (k == "--security") security = std::atoi(argv[i + 1]) != 0;
  }
  fs::path scratch = fs::temp_directory_path() / ("decima-bench-" + std::to_string(getpid()));
  fs::create_directories(scratch);
  if (!create_volume.empty()) {
    int rc = MeasureCreateVolume(scratch, create_volume, repeat);
    fs::remove_all(scratch);
    return rc;
  }
  if (volume.empty()) {
    volume = scratch / "phantom.nii";
    e2e::WriteTinyNifti(volume, 24, 24, 16);
  }
  if (security) {
    int rc = MeasureSecurity(scratch, volume, jobs);
    fs::remove_all(scratch);
    return rc;
  }
  nlohmann::json out;
  out["volume"] = volume.string();

  {
    e2e::ServerProcess server(scratch / "data1", {"--workers", "1"});
    std::string err;
    auto c = client::Connect(server.address(), "", {}, 30s, &err);
    std::string vol = MakeVolume(c, volume);
    std::vector<double> lat, job_s, overhead;
    for (int i = 0; i < jobs; ++i) {
      v1::Job j;
      lat.push_back(SubmitAndWait(c, vol, false, &j) * 1000);
      job_s.push_back(JobSeconds(j));
      if (double p = PipelineSeconds(j); p > 0) overhead.push_back((JobSeconds(j) - p) / p);
    }
    out["submit_to_running_ms"] = {
        {"p50", Median(lat)}, {"p90", Percentile(lat, 0.9)}, {"n", jobs}};
    out["job_seconds_idle_p50"] = Median(job_s);
    out["job_overhead_fraction_p50"] = Median(overhead);

    // Watchers: 100 extra watch streams on each job vs none.
    std::vector<double> with, without;
    for (int i = 0; i < 3; ++i) {
      v1::Job j;
      SubmitAndWait(c, vol, true, &j);
      without.push_back(JobSeconds(j));
    }
    for (int i = 0; i < 3; ++i) {
      auto stub = v1::Jobs::NewStub(c.channel);
      v1::CreateJobRequest req;
      req.mutable_spec()->set_volume(vol);
      req.mutable_spec()->set_image_size(128);
      v1::Job j;
      stub->CreateJob(c.Context().get(), req, &j);
      std::vector<std::thread> watchers;
      for (int k = 0; k < 100; ++k) {
        watchers.emplace_back([&] {
          v1::WatchJobRequest w;
          w.set_name(j.name());
          auto ctx = c.Context(false);
          auto reader = stub->WatchJob(ctx.get(), w);
          v1::JobEvent ev;
          while (reader->Read(&ev)) {
          }
          reader->Finish();
        });
      }
      for (auto& t : watchers) t.join();
      v1::GetJobRequest g;
      g.set_name(j.name());
      stub->GetJob(c.Context().get(), g, &j);
      with.push_back(JobSeconds(j));
    }
    out["watchers"] = {{"job_seconds_0_watchers_median", Median(without)},
                       {"job_seconds_100_watchers_median", Median(with)}};
  }

  for (bool fsync : {true, false}) {
    std::vector<std::string> extra = {"--max-upload-mb", "1024"};
    if (!fsync) extra.push_back("--no-fsync");
    e2e::ServerProcess server(scratch / (fsync ? "data2" : "data3"), extra);
    std::string cerr;
    auto c = client::Connect(server.address(), "", {}, 60s, &cerr);
    std::vector<double> rates;
    for (int rep = 0; rep < 3; ++rep) {
      fs::path blob = scratch / "blob.bin";
      {
        std::mt19937_64 rng(rep + (fsync ? 0 : 100));
        std::vector<uint64_t> buf(1 << 17);
        std::ofstream f(blob, std::ios::binary | std::ios::trunc);
        for (int m = 0; m < 256; ++m) {
          for (auto& x : buf) x = rng();
          f.write(reinterpret_cast<const char*>(buf.data()), 1 << 20);
        }
      }
      std::vector<client::InputFile> files;
      std::string err;
      client::CollectInputs(blob, &files, &err);
      client::HashInputs(&files, &err);
      auto t0 = std::chrono::steady_clock::now();
      grpc::Status s = client::UploadBlob(c, files[0], nullptr, 1, nullptr);
      double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      if (!s.ok()) std::fprintf(stderr, "upload: %s\n", s.error_message().c_str());
      rates.push_back(files[0].size / 1e6 / secs);
    }
    out[fsync ? "upload_mb_per_s_fsync" : "upload_mb_per_s_no_fsync"] = {{"median", Median(rates)},
                                                                         {"runs", rates}};
  }
  fs::remove_all(scratch);
  std::printf("%s\n", out.dump(2).c_str());
  return 0;
}
