#include <thread>

#include "gtest/gtest.h"
#include "server/store/event_bus.h"

namespace decima::server {
namespace {
using namespace std::chrono_literals;

v1::JobEvent Ev(int64_t seq, bool final_state = false) {
  v1::JobEvent e;
  e.set_sequence(seq);
  if (final_state) {
    e.mutable_state_change()->set_state(v1::SUCCEEDED);
  } else {
    e.mutable_progress()->set_stage("x");
  }
  return e;
}

TEST(EventBusTest, WaiterGetsEventsAfterItsSequenceInOrder) {
  EventBus bus(8);
  auto ch = bus.Subscribe("j");
  std::thread t([&] {
    for (int i = 1; i <= 3; ++i) bus.Publish("j", Ev(i));
  });
  t.join();
  std::vector<v1::JobEvent> out;
  ASSERT_EQ(ch->WaitAfter(1, 1s, &out), EventBus::Channel::Wait::kEvents);
  ASSERT_EQ(out.size(), 2u);
  EXPECT_EQ(out[0].sequence(), 2);
  EXPECT_EQ(out[1].sequence(), 3);
  out.clear();
  EXPECT_EQ(ch->WaitAfter(3, 20ms, &out), EventBus::Channel::Wait::kTimeout);
}

TEST(EventBusTest, EvictedEventsAreReportedAsAGap) {
  EventBus bus(2);
  auto ch = bus.Subscribe("j");
  for (int i = 1; i <= 5; ++i) bus.Publish("j", Ev(i));
  std::vector<v1::JobEvent> out;
  EXPECT_EQ(ch->WaitAfter(1, 1s, &out), EventBus::Channel::Wait::kGap);
  EXPECT_EQ(ch->WaitAfter(3, 1s, &out), EventBus::Channel::Wait::kEvents);
}

TEST(EventBusTest, FinalEventReachesSubscribersAndCloseWakesWaiters) {
  EventBus bus;
  auto ch = bus.Subscribe("j");
  bus.Publish("j", Ev(1, /*final_state=*/true));
  std::vector<v1::JobEvent> out;
  EXPECT_EQ(ch->WaitAfter(0, 1s, &out), EventBus::Channel::Wait::kEvents);
  auto ch2 = bus.Subscribe("k");
  std::thread t([&] {
    std::this_thread::sleep_for(20ms);
    bus.Close();
  });
  EXPECT_EQ(ch2->WaitAfter(0, 10s, &out), EventBus::Channel::Wait::kClosed);
  t.join();
}

}  // namespace
}  // namespace decima::server
