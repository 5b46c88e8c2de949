// The other process of tests/dds/dds_test.cpp: publishes a health sample (transient local) at
// once, then, when a features reader has matched, 20 features samples with known contents.
// Usage: dds_peer DOMAIN RIG_ID

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <thread>

#include "pulsetrack/dds/dds.hpp"

using namespace pulsetrack;

int main(int argc, char** argv) {
  if (argc != 3) {
    std::fprintf(stderr, "usage: dds_peer DOMAIN RIG_ID\n");
    return 2;
  }
  auto p = dds::Participant::create(static_cast<uint32_t>(std::atoi(argv[1])));
  if (!p) {
    std::fprintf(stderr, "%s\n", p.error().message.c_str());
    return 1;
  }
  auto health = dds::Writer::create(*p, dds::kHealthTopic, &pulsetrack_msgs_msg_dds__Health__desc,
                                    dds::Profile::kTransientLocal);
  auto features = dds::Writer::create(
      *p, dds::kFeaturesTopic, &pulsetrack_msgs_msg_dds__Features__desc, dds::Profile::kSensorData);
  if (!health || !features) return 1;
  pulsetrack_msgs_msg_dds__Health_ h{};
  h.header.stamp = dds::stamp(1'500'000'000);
  h.header.frame_id = const_cast<char*>("pulsetrack_left_camera");
  h.rig_id = argv[2];
  h.state = 1;
  h.state_text = const_cast<char*>("ok");
  h.source = const_cast<char*>("sim");
  h.source_state = const_cast<char*>("running");
  h.trigger_state = const_cast<char*>("software");
  h.recorder_state = const_cast<char*>("off");
  h.last_error = const_cast<char*>("");
  h.frames = 1234;
  if (!health->write(&h)) return 1;
  const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (features->matchedReaders() == 0 && std::chrono::steady_clock::now() < until)
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  pulsetrack_msgs_msg_dds__Feature_ list[3]{};
  pulsetrack_msgs_msg_dds__Features_ f{};
  f.header.frame_id = const_cast<char*>("pulsetrack_left_camera");
  f.rig_id = argv[2];
  f.features._buffer = list;
  f.features._length = 3;
  f.features._maximum = 3;
  f.features._release = false;
  for (uint64_t k = 0; k < 20; ++k) {
    f.frame = k;
    f.header.stamp = dds::stamp(static_cast<int64_t>(k) * 33'333'333);
    for (int i = 0; i < 3; ++i) {
      list[i].id = i;
      list[i].position = {0.001 * i, 0.002, 0.45 + 1e-6 * static_cast<double>(k)};
      list[i].ncc = 0.9F;
    }
    if (!features->write(&f)) return 1;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(1500));  // keep the health alive
  return 0;
}
