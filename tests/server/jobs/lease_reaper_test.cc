// LeaseReaper: lapsed leases go back to the queue on the reaper's own timer; live ones stay.
#include "server/jobs/lease_reaper.h"

#include <atomic>
#include <thread>

#include "gtest/gtest.h"
#include "tests/testing/test_data.h"

namespace decima::server {
namespace {

using namespace std::chrono_literals;

class LeaseReaperTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto s = OpenSqliteJobStore((testing::MakeScratchDir("lease_reaper") / "jobs.sqlite").string());
    ASSERT_TRUE(s.ok()) << s.status();
    store_ = std::move(*s);
    for (const char* id : {"a", "b"}) {
      v1::JobSpec spec;
      spec.set_volume("volumes/v");
      bool created = false;
      ASSERT_TRUE(store_->CreateJob(id, spec, "", 10, "", &created).ok());
    }
  }
  std::unique_ptr<JobStore> store_;
};

TEST_F(LeaseReaperTest, SweepRequeuesOnlyLapsedLeasesAndWakesTheWorkers) {
  ASSERT_TRUE(store_->ClaimNext("dead", -1000).ok());   // a: lapsed
  ASSERT_TRUE(store_->ClaimNext("alive", 60000).ok());  // b: held
  int wakes = 0;
  LeaseReaper reaper(store_.get(), 1h, 3, [&] { ++wakes; });
  auto n = reaper.SweepOnce();
  ASSERT_TRUE(n.ok()) << n.status();
  EXPECT_EQ(*n, 1u);
  EXPECT_EQ(wakes, 1);
  EXPECT_EQ(store_->GetJob("a")->state(), v1::QUEUED);
  EXPECT_EQ(store_->GetJob("b")->state(), v1::RUNNING);
  EXPECT_EQ(*reaper.SweepOnce(), 0u);
  EXPECT_EQ(wakes, 1) << "nothing re-queued, nobody woken";
}

TEST_F(LeaseReaperTest, ItsTimerRequeuesWithoutBeingAsked) {
  ASSERT_TRUE(store_->ClaimNext("dead", -1000).ok());
  std::atomic<int> wakes{0};
  LeaseReaper reaper(store_.get(), 20ms, 3, [&] { ++wakes; });
  reaper.Start();
  for (int i = 0; i < 250 && wakes.load() == 0; ++i) std::this_thread::sleep_for(20ms);
  reaper.Stop();
  EXPECT_EQ(wakes.load(), 1);
  EXPECT_EQ(store_->GetJob("a")->state(), v1::QUEUED);
}

}  // namespace
}  // namespace decima::server
