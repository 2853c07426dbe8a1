// The handlers over an in-process gRPC channel with the real stores: the guard on every
// service, each bad job spec refused at submit naming its field (message and ErrorDetail), the
// normalized spec stored, and the fault seam closed unless the server allows faults.
#include "server/api/service.h"
#include "tests/server/store/dicom_series_record.h"

#include <grpcpp/grpcpp.h>

#include <fstream>
#include <iterator>

#include "absl/strings/str_cat.h"
#include "core/io/volume_io.h"
#include "core/volume/volume.h"
#include "decima/v1/artifacts.grpc.pb.h"
#include "decima/v1/errors.pb.h"
#include "decima/v1/jobs.grpc.pb.h"
#include "decima/v1/uploads.grpc.pb.h"
#include "decima/v1/volumes.grpc.pb.h"
#include "gmock/gmock.h"
#include "google/protobuf/descriptor.pb.h"
#include "grpc/reflection/v1alpha/reflection.grpc.pb.h"
#include "gtest/gtest.h"
#include "server/jobs/job_memory.h"
#include "server/util/sha256.h"
#include "tests/server/jobs/bad_job_specs.h"
#include "tests/testing/test_data.h"

namespace decima::server {
namespace {

using ::testing::HasSubstr;
using ::testing::StartsWith;
namespace fs = std::filesystem;

constexpr char kToken[] = "s3cret";

class ServicesTest : public ::testing::Test {
 protected:
  void Start(bool allow_faults = false, Identities identities = Identities::SingleToken(kToken)) {
    dir_ = testing::MakeScratchDir("services");
    auto s = OpenSqliteJobStore((dir_ / "jobs.sqlite").string());
    ASSERT_TRUE(s.ok()) << s.status();
    store_ = std::move(*s);
    store_->SetListener(
        [this](const std::string& id, const v1::JobEvent& e) { bus_.Publish(id, e); });
    auto b = LocalBlobStore::Open(dir_ / "blobs", false);
    ASSERT_TRUE(b.ok()) << b.status();
    blobs_ = std::move(*b);
    WorkerPoolOptions wo;
    wo.owner = "test";
    pool_ = std::make_unique<WorkerPool>(store_.get(), wo);  // never started: jobs stay QUEUED
    ServiceOptions so;
    so.data_dir = DataDir(dir_);
    so.identities = std::move(identities);
    so.allow_faults = allow_faults;
    so.job_memory_cap_bytes = job_memory_cap_bytes_;
    services_ = std::make_unique<Services>(so, store_.get(), blobs_.get(), &bus_, pool_.get());
    grpc::ServerBuilder builder;
    builder.RegisterService(services_->uploads());
    builder.RegisterService(services_->volumes());
    builder.RegisterService(services_->jobs());
    builder.RegisterService(services_->artifacts());
    builder.RegisterService(services_->reflection());
    server_ = builder.BuildAndStart();
    ASSERT_TRUE(server_);
    channel_ = server_->InProcessChannel(grpc::ChannelArguments());
    v1::Volume vol;
    vol.set_name("volumes/v");
    bool created = false;
    ASSERT_TRUE(store_->CreateVolume("v", vol, "", "", &created).ok());
  }
  void TearDown() override {
    if (server_) server_->Shutdown();
  }
  std::unique_ptr<grpc::ClientContext> Ctx(const std::string& token = kToken) {
    auto ctx = std::make_unique<grpc::ClientContext>();
    if (!token.empty()) ctx->AddMetadata("authorization", "Bearer " + token);
    return ctx;
  }
  static v1::ErrorDetail Detail(const grpc::ClientContext& ctx) {
    v1::ErrorDetail d;
    auto md = ctx.GetServerTrailingMetadata();
    auto it = md.find("decima-error-bin");
    if (it != md.end()) d.ParseFromString(std::string(it->second.data(), it->second.size()));
    return d;
  }

  int64_t job_memory_cap_bytes_ = 0;  // ServiceOptions::job_memory_cap_bytes, set before Start
  fs::path dir_;
  EventBus bus_;
  std::unique_ptr<JobStore> store_;
  std::unique_ptr<BlobStore> blobs_;
  std::unique_ptr<WorkerPool> pool_;
  std::unique_ptr<Services> services_;
  std::unique_ptr<grpc::Server> server_;
  std::shared_ptr<grpc::Channel> channel_;
};

TEST_F(ServicesTest, EveryServiceRefusesAMissingOrWrongTokenAndServesTheRightOne) {
  Start();
  auto jobs = v1::Jobs::NewStub(channel_);
  auto vols = v1::Volumes::NewStub(channel_);
  auto ups = v1::Uploads::NewStub(channel_);
  auto arts = v1::Artifacts::NewStub(channel_);
  for (const std::string token : {"", "wrong"}) {
    v1::ListJobsResponse lj;
    EXPECT_EQ(jobs->ListJobs(Ctx(token).get(), {}, &lj).error_code(), grpc::UNAUTHENTICATED);
    v1::ListVolumesResponse lv;
    EXPECT_EQ(vols->ListVolumes(Ctx(token).get(), {}, &lv).error_code(), grpc::UNAUTHENTICATED);
    v1::UploadStatus us;
    EXPECT_EQ(ups->GetUploadStatus(Ctx(token).get(), {}, &us).error_code(), grpc::UNAUTHENTICATED);
    auto ctx = Ctx(token);
    auto reader = arts->ReadArtifact(ctx.get(), {});
    v1::ReadArtifactResponse chunk;
    while (reader->Read(&chunk)) {
    }
    EXPECT_EQ(reader->Finish().error_code(), grpc::UNAUTHENTICATED);
  }
  v1::ListJobsResponse lj;
  EXPECT_TRUE(jobs->ListJobs(Ctx().get(), {}, &lj).ok());
  services_->StartDraining();
  EXPECT_EQ(jobs->ListJobs(Ctx().get(), {}, &lj).error_code(), grpc::UNAVAILABLE);
}

// Reflection names every method and field of the API: only a caller the guard admits may ask.
TEST_F(ServicesTest, ReflectionAnswersOnlyAnIdentifiedCaller) {
  Start();
  namespace rv = ::grpc::reflection::v1alpha;
  auto stub = rv::ServerReflection::NewStub(channel_);
  auto ask = [&](const std::string& token, const std::vector<rv::ServerReflectionRequest>& reqs,
                 std::vector<rv::ServerReflectionResponse>* out) {
    auto ctx = Ctx(token);
    auto stream = stub->ServerReflectionInfo(ctx.get());
    // Request, answer, as the reflection clients do (the in-process transport does not buffer).
    for (const auto& r : reqs) {
      rv::ServerReflectionResponse resp;
      if (!stream->Write(r) || !stream->Read(&resp)) break;
      out->push_back(resp);
    }
    stream->WritesDone();
    return stream->Finish();
  };
  rv::ServerReflectionRequest list;
  list.set_list_services("");
  rv::ServerReflectionRequest symbol;
  symbol.set_file_containing_symbol("decima.v1.Jobs");
  rv::ServerReflectionRequest unknown;
  unknown.set_file_containing_symbol("decima.v1.NoSuchThing");
  for (const std::string token : {"", "wrong"}) {
    std::vector<rv::ServerReflectionResponse> out;
    EXPECT_EQ(ask(token, {list}, &out).error_code(), grpc::UNAUTHENTICATED) << token;
    EXPECT_TRUE(out.empty());
  }
  std::vector<rv::ServerReflectionResponse> out;
  ASSERT_TRUE(ask(kToken, {list, symbol, unknown}, &out).ok());
  ASSERT_EQ(out.size(), 3u);
  std::vector<std::string> names;
  for (const auto& s : out[0].list_services_response().service()) names.push_back(s.name());
  EXPECT_THAT(names, ::testing::IsSupersetOf({"decima.v1.Jobs", "decima.v1.Volumes",
                                              "decima.v1.Uploads", "decima.v1.Artifacts"}));
  // The defining file first, then what it imports, each a parseable FileDescriptorProto.
  const auto& files = out[1].file_descriptor_response().file_descriptor_proto();
  ASSERT_GE(files.size(), 2);
  google::protobuf::FileDescriptorProto first;
  ASSERT_TRUE(first.ParseFromString(files[0]));
  EXPECT_EQ(first.name(), "decima/v1/jobs.proto");
  ASSERT_EQ(first.service_size(), 1);
  EXPECT_EQ(first.service(0).name(), "Jobs");
  EXPECT_EQ(out[2].error_response().error_code(), grpc::NOT_FOUND);
  EXPECT_THAT(out[2].error_response().error_message(), HasSubstr("decima.v1.NoSuchThing"));
  // Broken requests get an error answer on the same stream, which goes on serving.
  rv::ServerReflectionRequest empty;  // no message_request
  rv::ServerReflectionRequest no_file;
  no_file.set_file_by_filename("../../etc/passwd" + std::string(4096, 'x'));
  rv::ServerReflectionRequest bad_extension;
  bad_extension.mutable_file_containing_extension()->set_containing_type("decima.v1.Job");
  bad_extension.mutable_file_containing_extension()->set_extension_number(-7);
  rv::ServerReflectionRequest no_type;
  no_type.set_all_extension_numbers_of_type("not a type");
  out.clear();
  ASSERT_TRUE(ask(kToken, {empty, no_file, bad_extension, no_type, list}, &out).ok());
  ASSERT_EQ(out.size(), 5u);
  EXPECT_EQ(out[0].error_response().error_code(), grpc::INVALID_ARGUMENT);
  for (int i = 1; i <= 3; ++i) {
    EXPECT_EQ(out[i].error_response().error_code(), grpc::NOT_FOUND) << i;
    EXPECT_FALSE(out[i].has_file_descriptor_response()) << i;
  }
  EXPECT_GE(out[4].list_services_response().service_size(), 4);
}

TEST_F(ServicesTest, EveryBadJobSpecIsInvalidArgumentAtSubmitNamingItsFieldAndQueuesNothing) {
  Start();
  auto jobs = v1::Jobs::NewStub(channel_);
  const auto cases = BadJobSpecs();
  ASSERT_GE(cases.size(), 20u);
  for (const auto& c : cases) {
    v1::CreateJobRequest req;
    req.mutable_spec()->set_volume("volumes/v");
    c.mutate(req.mutable_spec());
    v1::Job job;
    auto ctx = Ctx();
    grpc::Status s = jobs->CreateJob(ctx.get(), req, &job);
    EXPECT_EQ(s.error_code(), grpc::INVALID_ARGUMENT) << c.name << ": " << s.error_message();
    EXPECT_THAT(s.error_message(), StartsWith(c.field + ":")) << c.name;
    EXPECT_EQ(Detail(*ctx).field(), c.field) << c.name;
  }
  EXPECT_EQ(*store_->CountJobs(v1::QUEUED), 0);
}

TEST_F(ServicesTest, CreateJobStoresTheNormalizedSpecAndAnUnknownVolumeIsNotFound) {
  Start();
  auto jobs = v1::Jobs::NewStub(channel_);
  v1::CreateJobRequest req;
  req.mutable_spec()->set_volume("volumes/v");
  req.mutable_spec()->set_target_reduction(0);
  v1::Job job;
  ASSERT_TRUE(jobs->CreateJob(Ctx().get(), req, &job).ok());
  auto stored = store_->GetJob(job.name().substr(5));
  ASSERT_TRUE(stored.ok());
  const v1::JobSpec& s = stored->spec();
  EXPECT_EQ(s.policy(), v1::FIELD);
  EXPECT_EQ(s.regions(), 3);
  ASSERT_TRUE(s.has_target_reduction());
  EXPECT_EQ(s.target_reduction(), 0) << "an explicit 0 is kept";
  EXPECT_TRUE(s.weights().has_regional());
  EXPECT_EQ(s.image_size(), 512);
  EXPECT_EQ(s.views_size(), 1);

  req.mutable_spec()->set_volume("volumes/nope");
  EXPECT_EQ(jobs->CreateJob(Ctx().get(), req, &job).error_code(), grpc::NOT_FOUND);
}

// Issue 30: a job whose memory estimate is above the job limit is refused when it is submitted,
// naming the volume's size, the estimate, the limit and the flag, and nothing is queued; a job
// under the limit is queued as before.
TEST_F(ServicesTest, AJobOverTheMemoryLimitIsRefusedAtSubmitAndQueuesNothing) {
  job_memory_cap_bytes_ = int64_t{1} << 30;
  Start();
  v1::Volume big;
  big.set_name("volumes/big");
  for (int64_t d : {1024, 1024, 1024}) big.add_dims(d);
  bool created = false;
  ASSERT_TRUE(store_->CreateVolume("big", big, "", "", &created).ok());
  auto jobs = v1::Jobs::NewStub(channel_);
  v1::CreateJobRequest req;
  req.mutable_spec()->set_volume("volumes/big");
  v1::Job job;
  auto ctx = Ctx();
  grpc::Status s = jobs->CreateJob(ctx.get(), req, &job);
  EXPECT_EQ(s.error_code(), grpc::RESOURCE_EXHAUSTED) << s.error_message();
  EXPECT_THAT(s.error_message(), HasSubstr("volumes/big (1024x1024x1024 voxels) needs about"));
  EXPECT_THAT(s.error_message(), HasSubstr("more than the job limit of 1.0 GB"));
  EXPECT_THAT(s.error_message(), HasSubstr("--worker-memory-mb"));
  const v1::ErrorDetail detail = Detail(*ctx);
  EXPECT_EQ(detail.field(), "spec.volume");
  EXPECT_EQ(detail.limit(), "worker_memory_mb");
  EXPECT_EQ(detail.limit_value(), 1024);
  EXPECT_EQ(*store_->CountJobs(v1::QUEUED), 0);

  req.mutable_spec()->set_volume("volumes/v");  // no dims, no bytes: under any limit
  EXPECT_TRUE(jobs->CreateJob(Ctx().get(), req, &job).ok());
  EXPECT_EQ(*store_->CountJobs(v1::QUEUED), 1);
}

// Issue 30: a job that does not fit in memory but fits in slabs is queued simplified in slabs of
// kServerStreamSlabVoxels, the choice stored in its spec (GetJob shows it, every replica runs it
// so); CheckJobMemory answers the same before the upload. A spec that chose is kept: 0 (in memory)
// is refused with what slabs would need.
TEST_F(ServicesTest, AJobThatFitsOnlyInSlabsIsQueuedInSlabsAndTheChoiceIsStored) {
  v1::Volume ct;
  ct.set_name("volumes/ct");
  for (int64_t d : {511, 511, 400}) ct.add_dims(d);
  const int64_t in_memory = EstimateJobMemoryBytes(ct, 0, 0.5);
  const int64_t streamed = EstimateJobMemoryBytes(ct, kServerStreamSlabVoxels, 0.5);
  ASSERT_LT(streamed, in_memory);
  job_memory_cap_bytes_ = (streamed + in_memory) / 2;
  Start();
  bool created = false;
  ASSERT_TRUE(store_->CreateVolume("ct", ct, "", "", &created).ok());
  auto jobs = v1::Jobs::NewStub(channel_);

  v1::CheckJobMemoryRequest check;
  check.set_display_name("ct.nii.gz");
  for (int64_t d : ct.dims()) check.add_dims(d);
  v1::CheckJobMemoryResponse fits;
  grpc::Status s = jobs->CheckJobMemory(Ctx().get(), check, &fits);
  ASSERT_TRUE(s.ok()) << s.error_message();
  EXPECT_EQ(fits.stream_slab_voxels(), kServerStreamSlabVoxels);
  EXPECT_EQ(fits.estimate_mb(), (streamed + (1 << 20) - 1) >> 20);

  v1::CreateJobRequest req;
  req.mutable_spec()->set_volume("volumes/ct");
  v1::Job job;
  s = jobs->CreateJob(Ctx().get(), req, &job);
  ASSERT_TRUE(s.ok()) << s.error_message();
  EXPECT_TRUE(job.spec().has_stream_slab_voxels());
  EXPECT_EQ(job.spec().stream_slab_voxels(), kServerStreamSlabVoxels);
  auto stored = store_->GetJob(job.name().substr(5));
  ASSERT_TRUE(stored.ok()) << stored.status();
  EXPECT_EQ(stored->spec().stream_slab_voxels(), kServerStreamSlabVoxels);

  // In memory by choice: refused, and told what slabs would need.
  req.mutable_spec()->set_stream_slab_voxels(0);
  s = jobs->CreateJob(Ctx().get(), req, &job);
  EXPECT_EQ(s.error_code(), grpc::RESOURCE_EXHAUSTED) << s.error_message();
  EXPECT_THAT(s.error_message(), HasSubstr("simplified in slabs (stream_slab_voxels 16, or left "
                                           "unset) it would need about "));
  // A PSNR floor cannot be streamed: refused with the reason.
  req.mutable_spec()->clear_stream_slab_voxels();
  req.mutable_spec()->set_min_psnr(50);
  req.mutable_spec()->set_target_reduction(0.5);
  s = jobs->CreateJob(Ctx().get(), req, &job);
  EXPECT_EQ(s.error_code(), grpc::RESOURCE_EXHAUSTED) << s.error_message();
  EXPECT_THAT(s.error_message(), HasSubstr("no PSNR floor"));
  // A slab depth the pipeline refuses is named.
  req.mutable_spec()->clear_min_psnr();
  req.mutable_spec()->set_stream_slab_voxels(3);
  auto ctx = Ctx();
  s = jobs->CreateJob(ctx.get(), req, &job);
  EXPECT_EQ(s.error_code(), grpc::INVALID_ARGUMENT) << s.error_message();
  EXPECT_EQ(Detail(*ctx).field(), "spec.stream_slab_voxels");
  EXPECT_EQ(*store_->CountJobs(v1::QUEUED), 1);
}

// Issue 30: CheckJobMemory answers before any upload with CreateJob's decision on the same
// volume: the same code, message and detail (but naming dims), and refuses dims it cannot trust.
TEST_F(ServicesTest, CheckJobMemoryGivesCreateJobsDecisionBeforeTheVolumeExists) {
  job_memory_cap_bytes_ = int64_t{1} << 30;
  Start();
  auto jobs = v1::Jobs::NewStub(channel_);
  v1::CheckJobMemoryRequest req;
  req.set_display_name("head.nii.gz");
  req.set_size_bytes(12345);
  for (int64_t d : {64, 64, 32}) req.add_dims(d);
  v1::CheckJobMemoryResponse resp;
  grpc::Status s = jobs->CheckJobMemory(Ctx().get(), req, &resp);
  ASSERT_TRUE(s.ok()) << s.error_message();
  EXPECT_TRUE(resp.fits());
  EXPECT_EQ(resp.limit_mb(), 1024);
  v1::Volume small;
  for (int64_t d : {64, 64, 32}) small.add_dims(d);
  EXPECT_EQ(resp.estimate_mb(), (EstimateJobMemoryBytes(small) + (1 << 20) - 1) >> 20);
  EXPECT_GT(resp.estimate_mb(), 0);
  EXPECT_LE(resp.estimate_mb(), 1024);

  // Does not fit: CreateJob's refusal (the same message for the same dims), nothing queued.
  req.clear_dims();
  for (int64_t d : {1024, 1024, 1024}) req.add_dims(d);
  auto ctx = Ctx();
  s = jobs->CheckJobMemory(ctx.get(), req, &resp);
  EXPECT_EQ(s.error_code(), grpc::RESOURCE_EXHAUSTED) << s.error_message();
  EXPECT_THAT(s.error_message(), HasSubstr("head.nii.gz (1024x1024x1024 voxels) needs about"));
  EXPECT_THAT(s.error_message(), HasSubstr("more than the job limit of 1.0 GB"));
  EXPECT_THAT(s.error_message(), HasSubstr("--worker-memory-mb"));
  const v1::ErrorDetail detail = Detail(*ctx);
  EXPECT_EQ(detail.field(), "dims");
  EXPECT_EQ(detail.limit(), "worker_memory_mb");
  EXPECT_EQ(detail.limit_value(), 1024);
  v1::Volume big;
  big.set_name("volumes/big");
  for (int64_t d : {1024, 1024, 1024}) big.add_dims(d);
  bool created = false;
  ASSERT_TRUE(store_->CreateVolume("big", big, "", "", &created).ok());
  v1::CreateJobRequest create;
  create.mutable_spec()->set_volume("volumes/big");
  v1::Job job;
  grpc::Status cs = jobs->CreateJob(Ctx().get(), create, &job);
  EXPECT_EQ(cs.error_code(), s.error_code());
  const std::string tail = s.error_message().substr(s.error_message().find(" needs about"));
  EXPECT_THAT(cs.error_message(), HasSubstr(tail));
  EXPECT_EQ(*store_->CountJobs(v1::QUEUED), 0);

  // Bad dims: INVALID_ARGUMENT naming the field.
  const std::vector<std::pair<std::vector<int64_t>, std::string>> bad = {
      {{}, "dims"},
      {{64, 64}, "dims"},
      {{64, 64, 64, 1}, "dims"},
      {{64, 0, 64}, "dims"},
      {{64, -3, 64}, "dims"},
      {{(int64_t{1} << 31) + 1, 2, 2}, "dims"},
      {{int64_t{1} << 31, int64_t{1} << 31, int64_t{1} << 31}, "dims"},  // 2^93: overflows
      {{INT64_MAX, INT64_MAX, INT64_MAX}, "dims"},
  };
  for (const auto& [dims, field] : bad) {
    req.clear_dims();
    for (int64_t d : dims) req.add_dims(d);
    auto bctx = Ctx();
    s = jobs->CheckJobMemory(bctx.get(), req, &resp);
    EXPECT_EQ(s.error_code(), grpc::INVALID_ARGUMENT) << dims.size() << " " << s.error_message();
    EXPECT_THAT(s.error_message(), ::testing::StartsWith(field + ":"));
    EXPECT_EQ(Detail(*bctx).field(), field);
  }
  req.clear_dims();
  for (int64_t d : {8, 8, 8}) req.add_dims(d);
  req.set_size_bytes(-1);
  auto nctx = Ctx();
  s = jobs->CheckJobMemory(nctx.get(), req, &resp);
  EXPECT_EQ(s.error_code(), grpc::INVALID_ARGUMENT) << s.error_message();
  EXPECT_EQ(Detail(*nctx).field(), "size_bytes");

  // The caller check is CreateJob's: no token, no answer.
  req.set_size_bytes(1);
  EXPECT_EQ(jobs->CheckJobMemory(Ctx("").get(), req, &resp).error_code(), grpc::UNAUTHENTICATED);
}

// A job whose level record a queued level job will read cannot be deleted until that job has
// ended or is cancelled (the level job would fail when it runs).
TEST_F(ServicesTest, AJobIsNotDeletedWhileALevelJobReadsItsRecord) {
  Start();
  v1::JobSpec parent_spec;
  parent_spec.set_volume("volumes/v");
  bool created = false;
  ASSERT_TRUE(store_->CreateJob("parent", parent_spec, "", 0, "", &created).ok());
  ASSERT_TRUE(store_->Cancel("parent").ok());  // final, so deletable on its own
  v1::JobSpec level_spec = parent_spec;
  level_spec.set_levels_of("jobs/parent");
  ASSERT_TRUE(store_->CreateJob("level", level_spec, "", 0, "", &created).ok());
  auto jobs = v1::Jobs::NewStub(channel_);
  v1::DeleteJobRequest del;
  del.set_name("jobs/parent");
  v1::DeleteJobResponse resp;
  grpc::Status s = jobs->DeleteJob(Ctx().get(), del, &resp);
  EXPECT_EQ(s.error_code(), grpc::FAILED_PRECONDITION) << s.error_message();
  EXPECT_THAT(s.error_message(), HasSubstr("read by the level job jobs/level (QUEUED)"));
  EXPECT_TRUE(store_->GetJob("parent").ok()) << "refused, yet deleted";

  ASSERT_TRUE(store_->Cancel("level").ok());
  s = jobs->DeleteJob(Ctx().get(), del, &resp);
  EXPECT_TRUE(s.ok()) << s.error_message();
  EXPECT_FALSE(store_->GetJob("parent").ok());
}

TEST_F(ServicesTest, TheFaultSeamIsIgnoredUnlessTheServerAllowsFaults) {
  for (bool allow : {false, true}) {
    Start(allow);
    auto jobs = v1::Jobs::NewStub(channel_);
    v1::CreateJobRequest req;
    req.mutable_spec()->set_volume("volumes/v");
    auto ctx = Ctx();
    ctx->AddMetadata("decima-test-fault", "sleep:1");
    v1::Job job;
    ASSERT_TRUE(jobs->CreateJob(ctx.get(), req, &job).ok());
    const std::string fault = DataDir(dir_).ReadJobFault(job.name().substr(5));
    EXPECT_EQ(fault, allow ? "sleep:1" : "") << "allow_faults " << allow;
    auto bad = Ctx();
    bad->AddMetadata("decima-test-fault", "explode");
    grpc::Status s = jobs->CreateJob(bad.get(), req, &job);
    EXPECT_EQ(s.ok(), !allow) << s.error_message();
    TearDown();
    server_.reset();
  }
}

// Found by create_volume_fuzz: a manifest naming "s" and "s/IM2" answered INTERNAL
// ("materializing s/IM2: Not a directory"); it is the client's mistake, named by field.
TEST_F(ServicesTest, AManifestFileThatIsAlsoAFolderOfAnotherIsInvalidArgument) {
  Start();
  auto ups = v1::Uploads::NewStub(channel_);
  const std::string bytes = "plain file";
  Sha256 h;
  h.Update(bytes.data(), bytes.size());
  const std::string digest = h.HexDigest();
  v1::Blob blob;
  {
    auto ctx = Ctx();
    auto w = ups->Upload(ctx.get(), &blob);
    v1::UploadRequest r;
    r.set_sha256(digest);
    r.set_size_bytes(bytes.size());
    r.set_data(bytes);
    w->Write(r);
    w->WritesDone();
    ASSERT_TRUE(w->Finish().ok());
  }
  for (const auto& [first, second] :
       {std::pair<std::string, std::string>{"s", "s/IM2"}, {"a/b/c", "a/b"}}) {
    v1::CreateVolumeRequest req;
    for (const std::string& path : {first, second}) {
      auto* f = req.mutable_volume()->add_files();
      f->set_path(path);
      f->set_blob("blobs/" + digest);
    }
    auto ctx = Ctx();
    v1::Volume vol;
    grpc::Status s = v1::Volumes::NewStub(channel_)->CreateVolume(ctx.get(), req, &vol);
    EXPECT_EQ(s.error_code(), grpc::INVALID_ARGUMENT) << s.error_message();
    EXPECT_THAT(s.error_message(), HasSubstr("which is a file of the manifest"));
    EXPECT_THAT(Detail(*ctx).field(), StartsWith("volume.files["));
    EXPECT_FALSE(fs::exists(dir_ / "volumes") && !fs::is_empty(dir_ / "volumes"));
  }
}

std::string HexSha256(const std::string& s) {
  Sha256 h;
  h.Update(s.data(), s.size());
  return h.HexDigest();
}

// ListReceivedSeries: the store's receiver state through the handler; a reader sees every
// series, a submitter named as a sender's principal ("dicom:<calling AE>") its own, another
// submitter none; a bad token is INVALID_ARGUMENT.
TEST_F(ServicesTest, ListReceivedSeriesShowsStateAndReasonByOwner) {
  auto ids =
      Identities::Parse(absl::StrCat("token ", HexSha256("pacs"), " dicom:ORTHANC submitter\n",
                                     "token ", HexSha256("alice"), " alice submitter\n", "token ",
                                     HexSha256("rita"), " rita reader\n"),
                        "tokens");
  ASSERT_TRUE(ids.ok()) << ids.status();
  Start(false, *ids);
  const std::string aa(64, 'a'), bb(64, 'b');
  ASSERT_TRUE(
      store_->PutDicomInstance({"1.2.3", "i1", aa, "ORTHANC", "DECIMA", 1700000000000, 0, 1, ""})
          .ok());
  ASSERT_TRUE(
      store_->PutDicomInstance({"1.2.4", "k1", bb, "CT1", "DECIMA", 1700000001000, 0, 1, ""}).ok());
  DicomSeriesRecord incomplete =
      Check("set", "1.2.4", "", "incomplete: 1 slice(s) missing", v1::ReceivedSeries::INCOMPLETE);
  incomplete.calling_ae = "CT1";
  incomplete.last_received_ms = 1700000000500;
  // An earlier receive (another set than the one waiting now): its own entry, and the waiting
  // set is RECEIVING.
  ASSERT_TRUE(store_->PutDicomSeries(incomplete, {}).ok());
  DicomSeriesRecord queued = Check("set2", "1.2.5", "jobs/j1", "", v1::ReceivedSeries::QUEUED);
  queued.send_status = "sent: 3 instances";
  queued.calling_ae = "ORTHANC";
  queued.called_ae = "DECIMA";
  queued.instance_count = 113;
  queued.first_received_ms = 1700000002000;
  queued.last_received_ms = 1700000003000;
  ASSERT_TRUE(store_->PutDicomSeries(queued, {}).ok());

  auto stub = v1::Volumes::NewStub(channel_);
  auto list = [&](const std::string& token, v1::ListReceivedSeriesResponse* resp,
                  const std::string& page_token = "", int page_size = 0) {
    v1::ListReceivedSeriesRequest req;
    req.set_page_token(page_token);
    req.set_page_size(page_size);
    return stub->ListReceivedSeries(Ctx(token).get(), req, resp);
  };
  v1::ListReceivedSeriesResponse all;
  ASSERT_TRUE(list("rita", &all).ok());
  ASSERT_EQ(all.received_series_size(), 4);
  const v1::ReceivedSeries& newest = all.received_series(0);  // newest arrival first
  EXPECT_EQ(newest.series_instance_uid(), "1.2.5");
  EXPECT_EQ(newest.state(), v1::ReceivedSeries::QUEUED);
  EXPECT_EQ(newest.job(), "jobs/j1");
  EXPECT_EQ(newest.instance_count(), 113);
  EXPECT_EQ(newest.owner(), "dicom:ORTHANC");
  EXPECT_EQ(newest.send_status(), "sent: 3 instances");
  EXPECT_EQ(newest.last_receive_time().seconds(), 1700000003);
  EXPECT_EQ(all.received_series(1).series_instance_uid(), "1.2.4");
  EXPECT_EQ(all.received_series(1).state(), v1::ReceivedSeries::RECEIVING);
  EXPECT_EQ(all.received_series(1).calling_ae(), "CT1");
  EXPECT_EQ(all.received_series(2).state(), v1::ReceivedSeries::INCOMPLETE);
  EXPECT_EQ(all.received_series(2).calling_ae(), "CT1");
  EXPECT_EQ(all.received_series(3).state(), v1::ReceivedSeries::RECEIVING);

  // The waiting set of 1.2.4 checked (its key: sha256 of the sender and the sorted SOP
  // Instance UIDs, one a line; the receive: that at its newest arrival): INCOMPLETE with the
  // reason, and the earlier receive stays an entry of its own.
  incomplete.instance_set = HexSha256("CT1\nk1\n");
  incomplete.receive_key = incomplete.instance_set + "@1700000001000";
  incomplete.last_received_ms = 1700000001000;
  ASSERT_TRUE(store_->PutDicomSeries(incomplete, {}).ok());
  v1::ListReceivedSeriesResponse again;
  ASSERT_TRUE(list("rita", &again).ok());
  ASSERT_EQ(again.received_series_size(), 4);
  EXPECT_EQ(again.received_series(1).state(), v1::ReceivedSeries::INCOMPLETE);
  EXPECT_EQ(again.received_series(1).reason(), "incomplete: 1 slice(s) missing");
  EXPECT_EQ(again.received_series(2).state(), v1::ReceivedSeries::INCOMPLETE);
  EXPECT_EQ(again.received_series(3).state(), v1::ReceivedSeries::RECEIVING);

  v1::ListReceivedSeriesResponse own, none, page;
  ASSERT_TRUE(list("pacs", &own).ok());
  ASSERT_EQ(own.received_series_size(), 2);
  for (const auto& r : own.received_series()) EXPECT_EQ(r.owner(), "dicom:ORTHANC");
  ASSERT_TRUE(list("alice", &none).ok());
  EXPECT_EQ(none.received_series_size(), 0);
  ASSERT_TRUE(list("rita", &page, "", 2).ok());
  ASSERT_EQ(page.received_series_size(), 2);
  ASSERT_FALSE(page.next_page_token().empty());
  v1::ListReceivedSeriesResponse rest;
  ASSERT_TRUE(list("rita", &rest, page.next_page_token(), 2).ok());
  ASSERT_EQ(rest.received_series_size(), 2);
  EXPECT_TRUE(rest.next_page_token().empty());
  // A token past the end (the list shrank since, or it was made up) is an empty last page; the
  // largest offset must not wrap around to a token for the start.
  for (const std::string past : {"r4", "r1000000", "r18446744073709551615"}) {
    SCOPED_TRACE(past);
    v1::ListReceivedSeriesResponse empty;
    ASSERT_TRUE(list("rita", &empty, past, 2).ok());
    EXPECT_EQ(empty.received_series_size(), 0);
    EXPECT_TRUE(empty.next_page_token().empty());
  }
  v1::ListReceivedSeriesResponse bad;
  EXPECT_EQ(list("rita", &bad, "o7").error_code(), grpc::INVALID_ARGUMENT);
  EXPECT_EQ(list("rita", &bad, "r-1").error_code(), grpc::INVALID_ARGUMENT);
  EXPECT_EQ(list("wrong", &bad).error_code(), grpc::UNAUTHENTICATED);
}

// DeleteReceivedSeries: a sender's waiting instances go with their blobs, and the history keeps
// a DELETED entry. Only the series' owner ("dicom:<calling AE>") or an admin may delete it; a
// reader or another submitter gets PERMISSION_DENIED and nothing changes.
TEST_F(ServicesTest, DeleteReceivedSeriesIsTheOwnersOrAnAdminsAndFreesTheBlobs) {
  auto ids = Identities::Parse(
      absl::StrCat("token ", HexSha256("pacs"), " dicom:ORTHANC submitter\n", "token ",
                   HexSha256("alice"), " alice submitter\n", "token ", HexSha256("rita"),
                   " rita reader\n", "token ", HexSha256("root"), " root admin\n"),
      "tokens");
  ASSERT_TRUE(ids.ok()) << ids.status();
  Start(false, *ids);
  const std::string bytes = "DICM instance bytes";
  const std::string sha = HexSha256(bytes);
  {
    auto w = blobs_->OpenWriter(sha, static_cast<int64_t>(bytes.size()), 0);
    ASSERT_TRUE(w.ok()) << w.status();
    ASSERT_TRUE((*w)->Append(bytes.data(), bytes.size()).ok());
    ASSERT_TRUE((*w)->Commit().ok());
  }
  const int64_t size = static_cast<int64_t>(bytes.size());
  ASSERT_TRUE(
      store_->PutDicomInstance({"1.2.3", "i1", sha, "ORTHANC", "DECIMA", 1, 0, size, ""}).ok());
  ASSERT_TRUE(store_->PutDicomInstance({"1.2.3", "i1", sha, "CT1", "DECIMA", 2, 0, size, ""}).ok());
  auto stub = v1::Volumes::NewStub(channel_);
  auto del = [&](const std::string& token, const std::string& uid, const std::string& from,
                 v1::DeleteReceivedSeriesResponse* resp) {
    v1::DeleteReceivedSeriesRequest req;
    req.set_series_instance_uid(uid);
    req.set_calling_ae(from);
    return stub->DeleteReceivedSeries(Ctx(token).get(), req, resp);
  };
  v1::DeleteReceivedSeriesResponse resp;
  EXPECT_EQ(del("rita", "1.2.3", "", &resp).error_code(), grpc::PERMISSION_DENIED);
  EXPECT_EQ(del("alice", "1.2.3", "ORTHANC", &resp).error_code(), grpc::PERMISSION_DENIED);
  EXPECT_EQ(del("pacs", "1.2.3", "CT1", &resp).error_code(), grpc::PERMISSION_DENIED);
  EXPECT_EQ(store_->ListDicomInstances()->size(), 2u);
  EXPECT_EQ(del("pacs", "1.2.x", "", &resp).error_code(), grpc::INVALID_ARGUMENT);
  EXPECT_EQ(del("pacs", "1.2.9", "", &resp).error_code(), grpc::NOT_FOUND);

  // Every sender's it may delete: ORTHANC's only. CT1's instance holds the same bytes (one
  // blob), so the blob stays.
  ASSERT_TRUE(del("pacs", "1.2.3", "", &resp).ok());
  EXPECT_EQ(resp.deleted_instances(), 1);
  EXPECT_EQ(resp.freed_bytes(), 0);
  ASSERT_EQ(store_->ListDicomInstances()->size(), 1u);
  EXPECT_TRUE(blobs_->Has(sha));
  ASSERT_TRUE(del("root", "1.2.3", "CT1", &resp).ok());
  EXPECT_EQ(resp.deleted_instances(), 1);
  EXPECT_EQ(resp.freed_bytes(), size);
  EXPECT_TRUE(store_->ListDicomInstances()->empty());
  EXPECT_FALSE(blobs_->Has(sha));
  EXPECT_EQ(del("root", "1.2.3", "", &resp).error_code(), grpc::NOT_FOUND);

  v1::ListReceivedSeriesResponse listed;
  ASSERT_TRUE(stub->ListReceivedSeries(Ctx("rita").get(), {}, &listed).ok());
  ASSERT_EQ(listed.received_series_size(), 2);
  for (const auto& r : listed.received_series()) {
    EXPECT_EQ(r.state(), v1::ReceivedSeries::DELETED);
    EXPECT_EQ(r.instance_count(), 1);
  }
  EXPECT_EQ(listed.received_series(0).reason(), "deleted by root");
  EXPECT_EQ(listed.received_series(1).reason(), "deleted by dicom:ORTHANC");
}

// CreateVolume is idempotent on content per principal (issue 35 part 7): the caller's live
// volume of the same files is answered (reused, the first display name kept) whatever the
// request id, display name or whether the format was named; another name of the file, another
// principal or a deleted volume make a new one, and a reused create leaves no folder behind.
TEST_F(ServicesTest, CreateVolumeReusesOnlyTheCallersLiveVolumeOfTheSameFiles) {
  auto ids = Identities::Parse(absl::StrCat("token ", HexSha256("alice"), " alice submitter\n",
                                            "token ", HexSha256("bob"), " bob submitter\n"),
                               "tokens");
  ASSERT_TRUE(ids.ok()) << ids.status();
  Start(false, *ids);
  auto volume = MakeVolume({6, 5, 4}, VoxelType::kInt16);
  ASSERT_TRUE(volume.ok()) << volume.status();
  const fs::path nifti = dir_ / "head.nii";
  ASSERT_TRUE(io::WriteNifti(*volume, nifti).ok());
  auto sha = Sha256OfFile(nifti);
  ASSERT_TRUE(sha.ok()) << sha.status();
  {
    std::ifstream in(nifti, std::ios::binary);
    const std::string bytes((std::istreambuf_iterator<char>(in)), {});
    auto w = blobs_->OpenWriter(*sha, static_cast<int64_t>(bytes.size()), 0);
    ASSERT_TRUE(w.ok()) << w.status();
    ASSERT_TRUE((*w)->Append(bytes.data(), bytes.size()).ok());
    ASSERT_TRUE((*w)->Commit().ok());
  }
  auto stub = v1::Volumes::NewStub(channel_);
  auto create = [&](const std::string& token, const std::string& path,
                    const std::string& display_name, v1::VolumeFormat format,
                    const std::string& request_id) {
    v1::CreateVolumeRequest req;
    auto* f = req.mutable_volume()->add_files();
    f->set_path(path);
    f->set_blob("blobs/" + *sha);
    req.mutable_volume()->set_display_name(display_name);
    req.mutable_volume()->set_format(format);
    req.mutable_volume()->set_reused(true);  // output only: ignored on input
    req.set_request_id(request_id);
    v1::Volume vol;
    grpc::Status s = stub->CreateVolume(Ctx(token).get(), req, &vol);
    EXPECT_TRUE(s.ok()) << s.error_message();
    return vol;
  };
  const v1::Volume first = create("alice", "head.nii", "first", v1::VOLUME_FORMAT_UNSPECIFIED, "");
  EXPECT_FALSE(first.reused());
  const v1::Volume again = create("alice", "head.nii", "second", v1::VOLUME_FORMAT_NIFTI, "r2");
  EXPECT_EQ(again.name(), first.name());
  EXPECT_TRUE(again.reused());
  EXPECT_EQ(again.display_name(), "first");
  EXPECT_EQ(again.create_time().seconds(), first.create_time().seconds());
  v1::GetVolumeRequest get;
  get.set_name(first.name());
  v1::Volume stored;
  ASSERT_TRUE(stub->GetVolume(Ctx("alice").get(), get, &stored).ok());
  EXPECT_FALSE(stored.reused());

  const v1::Volume renamed = create("alice", "other.nii", "other", v1::VOLUME_FORMAT_NIFTI, "");
  EXPECT_NE(renamed.name(), first.name());
  EXPECT_FALSE(renamed.reused());
  const v1::Volume bobs = create("bob", "head.nii", "bob's", v1::VOLUME_FORMAT_UNSPECIFIED, "");
  EXPECT_NE(bobs.name(), first.name());
  EXPECT_FALSE(bobs.reused());
  EXPECT_EQ(bobs.creator(), "bob");
  EXPECT_EQ(bobs.display_name(), "bob's");
  EXPECT_TRUE(create("bob", "head.nii", "", v1::VOLUME_FORMAT_UNSPECIFIED, "").reused());

  v1::DeleteVolumeRequest del;
  del.set_name(first.name());
  v1::DeleteVolumeResponse deleted;
  ASSERT_TRUE(stub->DeleteVolume(Ctx("alice").get(), del, &deleted).ok());
  const v1::Volume after = create("alice", "head.nii", "third", v1::VOLUME_FORMAT_UNSPECIFIED, "");
  EXPECT_NE(after.name(), first.name());
  EXPECT_FALSE(after.reused());
  EXPECT_EQ(after.display_name(), "third");
  EXPECT_EQ(stub->GetVolume(Ctx("bob").get(), get, &stored).error_code(), grpc::NOT_FOUND);

  v1::ListVolumesResponse alices, bobs_list;
  ASSERT_TRUE(stub->ListVolumes(Ctx("alice").get(), {}, &alices).ok());
  ASSERT_TRUE(stub->ListVolumes(Ctx("bob").get(), {}, &bobs_list).ok());
  EXPECT_EQ(alices.volumes_size(), 2);
  EXPECT_EQ(bobs_list.volumes_size(), 1);
  // One folder per live volume: the reused creates removed what they had materialized.
  int folders = 0;
  for (const auto& e : fs::directory_iterator(dir_ / "volumes")) folders += e.is_directory();
  EXPECT_EQ(folders, 3);
}

// The request id prefix "dicom-" is the DICOM receiver's: a submitter who computes a series'
// id before it arrives cannot have the receiver take its job (or volume) as the sender's.
TEST_F(ServicesTest, RequestIdsWithTheReceiverPrefixAreRefused) {
  Start();
  auto jobs = v1::Jobs::NewStub(channel_);
  v1::CreateJobRequest req;
  req.mutable_spec()->set_volume("volumes/v");
  req.set_request_id("dicom-" + std::string(64, 'a'));
  v1::Job job;
  auto ctx = Ctx();
  grpc::Status s = jobs->CreateJob(ctx.get(), req, &job);
  EXPECT_EQ(s.error_code(), grpc::INVALID_ARGUMENT) << s.error_message();
  EXPECT_THAT(s.error_message(), HasSubstr("reserved for the DICOM receiver"));
  EXPECT_EQ(Detail(*ctx).field(), "request_id");
  EXPECT_EQ(*store_->CountJobs(v1::QUEUED), 0);
  auto vols = v1::Volumes::NewStub(channel_);
  v1::CreateVolumeRequest vreq;
  vreq.set_request_id("dicom-x");
  vreq.mutable_volume()->add_files()->set_path("a.nii");
  v1::Volume vol;
  auto vctx = Ctx();
  s = vols->CreateVolume(vctx.get(), vreq, &vol);
  EXPECT_EQ(s.error_code(), grpc::INVALID_ARGUMENT) << s.error_message();
  EXPECT_EQ(Detail(*vctx).field(), "request_id");
  // Other ids are the caller's as before.
  req.set_request_id("my-dicom-1");
  EXPECT_TRUE(jobs->CreateJob(Ctx().get(), req, &job).ok());
}

TEST(IdentitiesTest, TokensFileNamesTheLineAndKeepsOnlyHashes) {
  const std::string alice_sha = "9c220f200955d76c0a38d308225e0ef10c5f971acaf2f8d1d8f732affa5bd1dc";
  auto ids = Identities::Parse(
      "# comment\n\ntoken " + alice_sha + " alice submitter\ncert batch-host admin\n", "t");
  ASSERT_TRUE(ids.ok()) << ids.status();
  EXPECT_TRUE(ids->required());
  auto alice = ids->ForToken("alice-token");  // sha256("alice-token") is alice_sha
  ASSERT_TRUE(alice.has_value());
  EXPECT_EQ(alice->name, "alice");
  EXPECT_EQ(alice->role, Role::kSubmitter);
  EXPECT_FALSE(ids->ForToken(alice_sha).has_value());  // the hash is not the token
  EXPECT_FALSE(ids->ForToken("").has_value());
  EXPECT_EQ(ids->ForCertificate("batch-host").role, Role::kAdmin);
  EXPECT_EQ(ids->ForCertificate("unlisted").role, Role::kSubmitter);
  EXPECT_EQ(ids->ForCertificate("unlisted").name, "unlisted");

  struct Bad {
    std::string text, expect;
  };
  for (const Bad& b : std::vector<Bad>{
           {"token alice-token alice admin\n", "line 1: expected the token's sha256"},
           {"\ntoken " + alice_sha + " alice root\n", "line 2: role 'root'"},
           {"token " + alice_sha + " a admin\ncert a reader\n", "line 2: name 'a' appears twice"},
           {"key x y\n", "line 1: 'key': expected 'token' or 'cert'"},
           {"cert x\n", "line 1: expected 'cert <subject common name> <role>'"},
           {"# nothing\n", "no 'token' or 'cert' line"}}) {
    auto r = Identities::Parse(b.text, "tokens.txt");
    ASSERT_FALSE(r.ok()) << b.text;
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(std::string(r.status().message()), HasSubstr("tokens.txt"));
    EXPECT_THAT(std::string(r.status().message()), HasSubstr(b.expect)) << b.text;
  }
}

TEST(CallGuardTest, RolesAndOwnership) {
  const Principal alice{"alice", Role::kSubmitter}, rita{"rita", Role::kReader},
      root{"root", Role::kAdmin};
  EXPECT_TRUE(CallGuard::MayRead(alice, "alice", "jobs/a").ok());
  EXPECT_EQ(CallGuard::MayRead(alice, "bob", "jobs/a").error_code(), grpc::PERMISSION_DENIED);
  EXPECT_EQ(CallGuard::MayRead(alice, "", "jobs/a").error_code(), grpc::PERMISSION_DENIED);
  EXPECT_TRUE(CallGuard::MayRead(rita, "bob", "jobs/a").ok());
  EXPECT_EQ(CallGuard::MayWrite(rita, "rita", "jobs/a").error_code(), grpc::PERMISSION_DENIED);
  EXPECT_TRUE(CallGuard::MayWrite(root, "bob", "jobs/a").ok());
  EXPECT_EQ(CallGuard::MayCreate(rita, "jobs").error_code(), grpc::PERMISSION_DENIED);
  EXPECT_TRUE(CallGuard::MayCreate(alice, "jobs").ok());
  EXPECT_EQ(CallGuard::ListFilter(alice), "alice");
  EXPECT_EQ(CallGuard::ListFilter(rita), "");
  EXPECT_THAT(CallGuard::MayWrite(alice, "bob", "jobs/a").error_message(),
              HasSubstr("alice (submitter) may not change jobs/a"));
}

}  // namespace
}  // namespace decima::server
