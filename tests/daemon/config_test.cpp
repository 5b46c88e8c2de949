// pulsetrackd's config: the shipped file runs on the simulated rig; every bad input names
// file:line and the key.

#include "pulsetrack/daemon/config.hpp"

#include <gtest/gtest.h>

#include <filesystem>

namespace pulsetrack::daemon {
namespace {

const std::filesystem::path kShipped =
    std::filesystem::path(PULSETRACK_SOURCE_DIR) / "config" / "pulsetrackd.toml";

TEST(DaemonConfig, TheShippedFileRunsOnTheSimulatedRig) {
  auto c = loadDaemonConfig(kShipped);
  ASSERT_TRUE(c) << c.error().message;
  EXPECT_EQ(c->rig_id, "rig-0");
  EXPECT_EQ(c->source, SourceKind::kSim);
  EXPECT_TRUE(std::filesystem::exists(c->scene)) << c->scene;
  EXPECT_EQ(c->roi.left, cv::Rect(483, 339, 400, 340));
  EXPECT_EQ(c->roi.right, cv::Rect(476, 344, 400, 340));
  EXPECT_EQ(c->track.fifo_priority, 70);
  EXPECT_EQ(c->capture.cpu, -1);
  EXPECT_EQ(c->off_path.fifo_priority, 0);
  EXPECT_EQ(c->off_path.cpu, -1);
  auto pinned = parseDaemonConfig("[realtime]\noff_path = { cpu = 0 }\n", kShipped);
  ASSERT_TRUE(pinned) << pinned.error().message;
  EXPECT_EQ(pinned->off_path.cpu, 0);
  EXPECT_DOUBLE_EQ(c->fps, 30.0);
  EXPECT_EQ(c->tracker.stereo_refresh, 25);
  EXPECT_EQ(c->tracker.template_refresh, 25);
  EXPECT_DOUBLE_EQ(c->tracker.min_stereo_confirmed, 0.25);
  EXPECT_EQ(c->tracker_scale, 0.0);  // auto
  EXPECT_EQ(c->sim_faults.missing_trigger_every + c->sim_faults.left_drop_every +
                c->sim_faults.right_miss_every,
            0);  // no injected faults as shipped
  // The file as shipped states the defaults: an empty file gives the same.
  auto d = parseDaemonConfig("", kShipped);
  ASSERT_TRUE(d);
  EXPECT_EQ(d->rig_id, c->rig_id);
  EXPECT_EQ(d->scene, c->scene);
  EXPECT_EQ(d->roi.left, c->roi.left);
  EXPECT_EQ(d->publish.fifo_priority, c->publish.fifo_priority);
  EXPECT_EQ(d->health_period_ms, c->health_period_ms);
  EXPECT_EQ(d->topics.features, "rt/pulsetrack/features");
  EXPECT_EQ(d->retry_interval_s, c->retry_interval_s);
  EXPECT_EQ(d->velocity_window_s, c->velocity_window_s);
  EXPECT_EQ(d->tracker.min_stereo_confirmed, c->tracker.min_stereo_confirmed);
  EXPECT_EQ(d->tracker.stereo_refresh, c->tracker.stereo_refresh);
  // The shipped [field] says what the defaults are.
  EXPECT_TRUE(c->field.enabled);
  EXPECT_EQ(c->field.spacing_mm, d->field.spacing_mm);
  EXPECT_EQ(c->field.smoothing, d->field.smoothing);
  EXPECT_EQ(c->field.reach, d->field.reach);
  EXPECT_EQ(c->field.max_grid_points, d->field.max_grid_points);
  EXPECT_EQ(d->topics.field, "rt/pulsetrack/field");
  EXPECT_EQ(c->sim_faults.outage_every_s, 0.0);
  EXPECT_EQ(d->record_min_free_mb, c->record_min_free_mb);
  EXPECT_EQ(c->record_min_free_mb, 1024);
  EXPECT_TRUE(c->record_resume);
  auto ns = parseDaemonConfig("[dds]\nnamespace = \"/site/or1\"\n", kShipped);
  ASSERT_TRUE(ns) << ns.error().message;
  EXPECT_EQ(ns->topics.command, "rt/site/or1/pulsetrack/command");
}

TEST(DaemonConfig, OneV4l2DeviceCarryingBothViews) {
  auto c = parseDaemonConfig(
      "[source]\nkind = \"v4l2\"\nrig = \"rigs/scope.yaml\"\nlayout = \"sbs\"\n"
      "[source.device]\ndevice = \"/dev/video2\"\npixel_format = \"YUYV\"\n",
      "/etc/pulsetrack/pulsetrackd.toml");
  ASSERT_TRUE(c) << c.error().message;
  EXPECT_EQ(c->layout, drivers::StereoLayout::kSideBySide);
  EXPECT_EQ(c->device_camera.device, "/dev/video2");
  EXPECT_EQ(c->device_camera.pixel_format, "YUYV");
  EXPECT_EQ(c->device_camera.width, 0);  // the rig's views, side by side
  auto tb = parseDaemonConfig("[source]\nkind = \"v4l2\"\nrig = \"r.yaml\"\nlayout = \"tb\"\n",
                              "/etc/p.toml");
  ASSERT_TRUE(tb) << tb.error().message;
  EXPECT_EQ(tb->layout, drivers::StereoLayout::kTopBottom);
  EXPECT_EQ(tb->device_camera.device, "/dev/video0");
}

void expectError(const std::string& text, const std::string& needle) {
  auto c = parseDaemonConfig(text, "/etc/pulsetrack/pulsetrackd.toml");
  ASSERT_FALSE(c) << text;
  EXPECT_NE(c.error().message.find(needle), std::string::npos)
      << "message: " << c.error().message << "\nexpected: " << needle;
}

TEST(DaemonConfig, SecurityNamesAnEnclaveOrEveryFile) {
  // Shipped: no [security] (unsecured, lab use).
  auto c = parseDaemonConfig("", "/etc/pulsetrack/pulsetrackd.toml");
  ASSERT_TRUE(c);
  EXPECT_FALSE(c->security.has_value());
  // An enclave, relative to the config file's folder; one file overridden.
  c = parseDaemonConfig(
      "[security]\nenclave = \"keystore/enclaves/pulsetrack/daemon\"\n"
      "permissions = \"/srv/p.p7s\"\n",
      "/etc/pulsetrack/pulsetrackd.toml");
  ASSERT_TRUE(c) << c.error().message;
  const std::optional<dds::SecurityFiles>& security = c->security;
  ASSERT_TRUE(security.has_value());
  const dds::SecurityFiles files = security.value_or(dds::SecurityFiles{});
  EXPECT_EQ(files.certificate, "/etc/pulsetrack/keystore/enclaves/pulsetrack/daemon/cert.pem");
  EXPECT_EQ(files.governance, "/etc/pulsetrack/keystore/enclaves/pulsetrack/daemon/governance.p7s");
  EXPECT_EQ(files.permissions, "/srv/p.p7s");
  // Neither an enclave nor all six files; a domain DDS Security cannot use; an unknown key.
  expectError("[security]\ncertificate = \"c.pem\"\n", "[security] needs enclave = \"DIR\"");
  expectError("[dds]\ndomain_id = 231\n[security]\nenclave = \"e\"\n",
              "[dds] domain_id 231 with [security]: DDS Security's domains are 0-230");
  expectError("[security]\nenclave = \"e\"\ncert = \"c.pem\"\n", "security.cert");
}

// fuzz_daemon_config's finding: a character outside ASCII where TOML expects whitespace or a key
// (here U+0497) made toml++ 3.3 reach __builtin_unreachable (undefined behaviour). It is refused
// before toml++ sees it; in strings and comments, where TOML allows it, it still reads.
TEST(DaemonConfig, ACharacterOutsideAsciiOutsideAStringIsNamedNotUndefined) {
  expectError("\xd2\x97", "pulsetrackd.toml:1: a character outside ASCII outside a string");
  expectError("rig_id = \"a\"\n\n[dds] \xc2\xa1\n", "pulsetrackd.toml:3: a character outside");
  auto ok = parseDaemonConfig(
      "# Salle d'op\xc3\xa9ration 1\nrig_id = \"bloc-\xc3\xa9\"\n"
      "[source]\nscene = \"\"\"multi\n\xc3\xa9\"\"\"\n",
      kShipped);
  ASSERT_TRUE(ok) << ok.error().message;
  EXPECT_EQ(ok->rig_id, "bloc-\xc3\xa9");
  // A multi-line string may end with one or two quotes of its own before the delimiter: the
  // scan must not take the extra quote for the start of a new string (review finding).
  expectError("rig_id = \"\"\"x\"\"\"\" \xd2\x97\n", "pulsetrackd.toml:1: a character outside");
  expectError("rig_id = '''x'''' \xd2\x97\n", "pulsetrackd.toml:1: a character outside");
  // A longer run's finding: a quote right after a number is no string to toml++ (it reads on
  // as the number's garbage and reached the same unreachable point on the U+039A inside).
  expectError("track = { priority =7777777777777777777777555555555555555555\"rig-\xce\x9a\"\n",
              "pulsetrackd.toml:1: a character outside ASCII outside a string");
  expectError("a = \"x\"\"\xce\x9a\"\n", "pulsetrackd.toml:1: a character outside");
  // Where TOML has strings, non-ASCII still reads: values, arrays across lines, quoted keys,
  // inline tables (refused by the config's reader as unknown keys, not by the pre-scan).
  auto strings = parseDaemonConfig(
      "rig_id = \"\xce\x9a\"\n\"\xce\x9a\".x = 1\n[tracker]\n\"\xce\x9a\" = [\n  \"\xce\x9a\",\n"
      "  '\xce\x9a' ]\nt = { \"\xce\x9a\" = \"\xce\x9a\" }\n",
      kShipped);
  ASSERT_FALSE(strings);
  EXPECT_EQ(strings.error().message.find("outside ASCII"), std::string::npos)
      << strings.error().message;
  // A byte order mark is not a character of the file.
  auto bom = parseDaemonConfig("\xEF\xBB\xBFrig_id = \"a\"\n", kShipped);
  ASSERT_TRUE(bom) << bom.error().message;
  EXPECT_EQ(bom->rig_id, "a");
}

TEST(DaemonConfig, BadInputNamesFileLineAndKey) {
  expectError("rig_id = \"a\"\n[tracker]\nroi_lft = [1, 2, 3, 4]\n",
              "pulsetrackd.toml:3: unknown key 'tracker.roi_lft'");
  expectError("[dds]\ndomain_id = 300\n", "pulsetrackd.toml:2: dds.domain_id: expected an integer");
  expectError("[dds]\ndomain_id = \"7\"\n", "dds.domain_id");
  expectError("[source]\nkind = \"usb\"\n",
              "source.kind: expected one of libcamera, replay, sim, v4l2");
  expectError("[source]\nkind = \"replay\"\n", "source.recording is required");
  expectError("[tracker]\nroi_left = [1, 2, 3]\n", "tracker.roi_left: expected 4 to 4 numbers");
  expectError("[tracker]\nroi_left = [1.5, 2, 3, 4]\n", "tracker.roi_left: expected 4 whole");
  expectError("[tracker]\nroi_left = [1, 2, 0, 4]\n", "width and height must be positive");
  expectError("[realtime]\ntrack = { priority = 120 }\n",
              "pulsetrackd.toml:2: realtime.track.priority");
  expectError("[realtime]\ntrack = { prio = 1 }\n", "unknown key 'realtime.track.prio'");
  expectError("[realtime]\noff_path = { priority = 10 }\n",
              "[realtime] off_path priority is 10: the stages off the features' path run at "
              "normal priority (0)");
  expectError("rig_id = \n", "pulsetrackd.toml:1:");  // a syntax error
  expectError("rig_id = \"\"\n", "rig_id must not be empty");
  expectError("[source.faults]\nmissing_trigger_every = -1\n",
              "pulsetrackd.toml:2: source.faults.missing_trigger_every");
  expectError("[source]\nkind = \"v4l2\"\n",
              "source.rig (the rig's calibration) is required with kind = \"v4l2\"");
  expectError("[source]\nkind = \"libcamera\"\nrig = \"r.yaml\"\n", "source.left.libcamera_id and");
  expectError("[dds]\nnamespace = \"or 1\"\n",
              "pulsetrackd.toml: [dds] namespace: DDS namespace 'or 1': ' ' is not allowed");
  expectError("[dds]\nnamespace = \"1or\"\n", "a segment starts with a digit");
  expectError("[source]\nlossless = true\n", "source.lossless: only a replay");
  expectError("[tracker]\nretry_interval_s = 0\n", "tracker.retry_interval_s");
  expectError("[tracker]\nvelocity_window_s = 20\n", "tracker.velocity_window_s");
  expectError("[field]\nspacing_mm = 0.01\n", "pulsetrackd.toml:2: field.spacing_mm");
  expectError("[field]\nsmoothing = 0\n", "field.smoothing");
  expectError("[field]\nreach = 0.5\n", "field.reach");
  expectError("[field]\nspacing = 1.0\n", "field.spacing");  // an unknown key
  expectError("[source.left]\npixel_format = \"RGB\"\n",
              "source.left.pixel_format: expected one of");
  expectError("[source.right]\nbuffers = 1\n", "pulsetrackd.toml:2: source.right.buffers");
  expectError("[trigger]\nkind = \"usb\"\n", "trigger.kind: expected one of box, none");
  // One device carrying both views (a microscope's side-by-side output): v4l2 only, described in
  // [source.device], no trigger box; two cameras are not described there.
  expectError("[source]\nlayout = \"sbs\"\n",
              "source.layout = \"sbs\" (one device carrying both views) is for kind = \"v4l2\"");
  expectError("[source]\nkind = \"v4l2\"\nrig = \"r.yaml\"\nlayout = \"lr\"\n",
              "source.layout: expected one of sbs, tb, two");
  expectError(
      "[source]\nkind = \"v4l2\"\nrig = \"r.yaml\"\nlayout = \"sbs\"\n[source.left]\n"
      "device = \"/dev/video3\"\n",
      "describe it in [source.device], not [source.left] / [source.right]");
  expectError("[source]\nkind = \"v4l2\"\nrig = \"r.yaml\"\n[source.device]\nwidth = 2720\n",
              "[source.device] is for one device carrying both views");
  expectError(
      "[source]\nkind = \"v4l2\"\nrig = \"r.yaml\"\nlayout = \"tb\"\n[trigger]\nkind = "
      "\"box\"\n",
      "[trigger] kind = \"box\" with one device carrying both views");
  expectError("[recorder]\nslots = 1\n", "recorder.slots");
  expectError("[tracker]\nmax_features = 50\nstereo_refresh = 60\n",
              "pulsetrackd.toml:3: tracker.stereo_refresh");
  expectError("[tracker]\nmax_features = 50\ntemplate_refresh = 51\n",
              "pulsetrackd.toml:3: tracker.template_refresh");
  expectError("[tracker]\nscale = \"0.7\"\n", "pulsetrackd.toml:2: tracker.scale");
  expectError("[tracker]\nmin_stereo_confirmed = 1.5\n",
              "pulsetrackd.toml:2: tracker.min_stereo_confirmed");
  expectError("[source.faults]\nright_drop_every = 3\n",
              "unknown key 'source.faults.right_drop_every'");
  expectError(
      "[source]\nkind = \"replay\"\nrecording = \"r\"\n[source.faults]\nleft_drop_every = 3\n",
      "only the simulated rig");
  expectError("[source.faults]\noutage_every_s = 60.0\n",
              "outage_every_s and outage_s go together");
  expectError("[source.faults]\noutage_every_s = 5.0\noutage_s = 5.0\n",
              "outage_s (5) must be shorter than outage_every_s (5)");
  expectError(
      "[source]\nkind = \"replay\"\nrecording = \"r\"\n[source.faults]\noutage_every_s = "
      "60.0\noutage_s = 4.0\n",
      "and a replay at a rate (pace = \"rate\") missing triggers and outages");
  expectError("[recorder]\nmin_free_mb = -5\n", "recorder.min_free_mb");
  // A replay at a rate shows missing triggers and outages, as a live camera would.
  auto rate = parseDaemonConfig(
      "[source]\nkind = \"replay\"\nrecording = \"r\"\npace = \"rate\"\n[source.faults]\n"
      "missing_trigger_every = 997\noutage_every_s = 300.0\noutage_s = 4.0\n[recorder]\n"
      "min_free_mb = 256\nresume = false\n",
      "/etc/pulsetrack/pulsetrackd.toml");
  ASSERT_TRUE(rate) << rate.error().message;
  EXPECT_EQ(rate->sim_faults.missing_trigger_every, 997);
  EXPECT_EQ(rate->sim_faults.outage_every_s, 300.0);
  EXPECT_EQ(rate->sim_faults.outage_s, 4.0);
  EXPECT_EQ(rate->record_min_free_mb, 256);
  EXPECT_FALSE(rate->record_resume);
  auto missing = loadDaemonConfig("/nonexistent/pulsetrackd.toml");
  ASSERT_FALSE(missing);
  EXPECT_NE(missing.error().message.find("/nonexistent/pulsetrackd.toml: cannot open"),
            std::string::npos);
}

}  // namespace
}  // namespace pulsetrack::daemon
