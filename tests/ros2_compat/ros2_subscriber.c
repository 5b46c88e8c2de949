// ros2_subscriber: a DDS subscriber that receives pulsetrackd's topics the way a ROS 2 node
// (rclcpp/rclpy over rmw_cyclonedds_cpp) does, and shares nothing with the daemon: its types come
// from the ROS 2 .msg files (msg2idl.py -> ros2_types.idl -> idlc -t), not from msgs/idl, and it
// uses Cyclone's C API directly, not pulsetrack's dds/ layer.
//
// What makes it a ROS 2 subscriber on the wire (rmw_cyclonedds_cpp, Humble):
// - topic names "rt/" + the ROS name: rt/[<ns>/]pulsetrack/{features,deformation,health};
// - type names <pkg>::msg::dds_::<Name>_, keyless (no @key), final, members in .msg order;
// - XCDR1 only (rmw_cyclonedds's sertype allows only DDS_DATA_REPRESENTATION_FLAG_XCDR1);
// - no type information (idlc -t; rmw_cyclonedds registers its sertype without it), so Cyclone
//   matches the daemon's writers by topic and type name, as it does for a ROS 2 node;
// - the QoS rmw_cyclonedds derives from rclcpp's profiles (create_readwrite_qos in rmw_node.cpp).
//
// usage: ros2_subscriber --domain N [--namespace NS] [--features N] [--deformation N]
//                        [--health N] [--field N] [--timeout S]
// --features/--deformation/--health: samples to wait for (default 1 each, 0: don't wait);
// --field: sensor_msgs/PointCloud2 samples of rt/[NS/]pulsetrack/field (default 0), decoded as
// rviz2 and PCL decode a cloud: each channel found by its name in `fields`, read at its declared
// offset in each point_step with its declared datatype and the cloud's is_bigendian.
// Prints one line per sample to stdout (flushed), space-separated key=value; free-text strings
// are always "quoted" (C escapes: \" \\ \n \t \xHH), rig and frame_id only when they need it;
// doubles %.17g (features' x0 y0 z0 %.9g, nan without features; health fps %.9g), bools 0/1:
//   features frame sec nanosec rig n ok(=status 0) first_id(-1: none) x0 y0 z0 status0 reason0
//            lx0 ly0 rx0 ry0 (its pixels), lxmin lymin lxmax lymax (the ok features' left pixels'
//            bounding box) frame_id
//   deformation frame sec nanosec rig dx dy dz vx vy vz ok total cx cy cz velocity_delay
//            displacement_sigma velocity_sigma detections continuous np (horizons), per horizon k:
//            phk pdxk pdyk pdzk psk pmk, frame_id
//   health sec nanosec rig state state_text last_error source source_state trigger_state
//            recorder_state tracking_state clock_state security_state output_state
//            clock_synchronized fps frames drops deadline_misses unpaired missing_triggers
//            source_faults recorder_faults commands_accepted commands_refused
//            stages="name:p50/p99/max,..." frame_id
//   field sec nanosec width height point_step row_step bytes is_bigendian is_dense
//            fields="name:offset:datatype:count,..." points valid(=finite x y z) mean_dx mean_dy
//            mean_dz (over the valid points, m) mean_confidence min_z max_z, the middle grid
//            point's mx my mz mdx mdy mdz mconf, missing="names not found" frame_id
//   tracked sec nanosec frame set_id signal n, per target k: rkx rky rkz pkx pky pkz dkx dky dkz ck
//   image side sec nanosec format bytes jpeg(=1: starts with SOI, ends with EOI) width height
//            (from the JPEG's SOF marker, as a decoder reads them; 0 when none) frame_id
// --images N: sensor_msgs/CompressedImage samples of each of rt/[NS/]pulsetrack/{left,right}/
// image/compressed (default 0), with image_transport's subscriber QoS (SensorDataQoS).
// --targets "x,y,z;x,y,z" (m) [--targets-frame reference|latest]: publishes one
// pulsetrack_msgs/Targets set (set_id 42, or --set-id N) first, as a ROS 2 node with
// rclcpp::QoS(1).reliable().transient_local(); --tracked N: TrackedTargets samples to wait for.
// then "summary features=N deformation=N health=N field=N tracked=N". Exit 0: every requested count
// reached; 1: timeout (or interrupted) first, with what matched on stderr; 2: bad usage or a DDS
// error (named on stderr).
#define _POSIX_C_SOURCE 200809L

#include <dds/dds.h>
#include <errno.h>
#include <inttypes.h>
#include <math.h>
#include <signal.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "ros2_types.h"

enum { kFeatures, kDeformation, kHealth, kField, kTracked, kImageLeft, kImageRight, kTopics };

static const char* const kLeaf[kTopics] = {"features",
                                           "deformation",
                                           "health",
                                           "field",
                                           "targets_tracked",
                                           "left/image/compressed",
                                           "right/image/compressed"};

static volatile sig_atomic_t g_stop = 0;

static void onSignal(int sig) {
  (void)sig;
  g_stop = 1;
}

static void usage(FILE* out) {
  fprintf(out,
          "usage: ros2_subscriber --domain N [--namespace NS] [--features N] [--deformation N]\n"
          "       [--command start|stop|redetect|set_roi] (publishes one Command first)\n"
          "                       [--health N] [--field N] [--timeout S]\n"
          "       [--targets \"x,y,z;...\" [--targets-frame reference|latest] [--set-id N]]\n"
          "       [--tracked N] [--images N]\n"
          "Subscribes to rt/[NS/]pulsetrack/{features,deformation,health} as a ROS 2 node over\n"
          "rmw_cyclonedds_cpp would (types from the .msg files, ROS 2 QoS, XCDR1, keyless) and\n"
          "prints one line per sample. --features/--deformation/--health: samples to wait for\n"
          "(default 1 each; 0: don't wait for that topic). --field N: PointCloud2 samples of\n"
          "rt/[NS/]pulsetrack/field (default 0). --timeout: seconds (default 30).\n"
          "Exit 0 when every count is reached, 1 on timeout, 2 on usage or DDS errors.\n"
          "DDS configuration: CYCLONEDDS_URI from the environment.\n");
}

static bool parseU32(const char* s, uint32_t max, uint32_t* out) {
  if (s == NULL || *s == '\0' || *s == '-' || *s == '+') return false;
  char* end = NULL;
  errno = 0;
  const unsigned long v = strtoul(s, &end, 10);
  if (errno != 0 || *end != '\0' || v > max) return false;
  *out = (uint32_t)v;
  return true;
}

static bool parseSeconds(const char* s, double* out) {
  if (s == NULL || *s == '\0') return false;
  char* end = NULL;
  errno = 0;
  const double v = strtod(s, &end);
  if (errno != 0 || *end != '\0' || !(v > 0.0) || v > 1e6) return false;
  *out = v;
  return true;
}

// ROS 2 namespace rules, as pulsetrackd checks them: segments of letters, digits and '_'
// separated by '/', none starting with a digit; one leading '/' allowed (absolute form).
static bool validNamespace(const char* ns) {
  bool segment_start = true;
  for (const char* p = ns; *p; ++p) {
    const char c = *p;
    if (c == '/') {
      if (segment_start) return false;
      segment_start = true;
      continue;
    }
    const bool alpha = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || c == '_';
    const bool digit = c >= '0' && c <= '9';
    if (!alpha && !digit) return false;
    if (segment_start && digit) return false;
    segment_start = false;
  }
  return !segment_start;
}

static int64_t monotonicNs(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

// A string value: "..." with C escapes, so that a line stays one line and splits on spaces.
static void putQuoted(const char* s) {
  putchar('"');
  for (const unsigned char* p = (const unsigned char*)(s ? s : ""); *p; ++p) {
    switch (*p) {
      case '"':
        fputs("\\\"", stdout);
        break;
      case '\\':
        fputs("\\\\", stdout);
        break;
      case '\n':
        fputs("\\n", stdout);
        break;
      case '\r':
        fputs("\\r", stdout);
        break;
      case '\t':
        fputs("\\t", stdout);
        break;
      default:
        if (*p < 0x20 || *p == 0x7f)
          printf("\\x%02x", *p);
        else
          putchar(*p);
    }
  }
  putchar('"');
}

// A name-like string value (rig id, frame id): bare if it needs no quoting, else quoted.
static void putToken(const char* s) {
  const char* v = s ? s : "";
  bool bare = *v != '\0';
  for (const unsigned char* p = (const unsigned char*)v; *p && bare; ++p)
    bare = *p > 0x20 && *p < 0x7f && *p != '"' && *p != '\\' && *p != '=';
  if (bare)
    fputs(v, stdout);
  else
    putQuoted(v);
}

static void printStamp(const std_msgs_msg_dds__Header_* h) {
  printf(" sec=%" PRId32 " nanosec=%" PRIu32, h->stamp.sec, h->stamp.nanosec);
}

static void printFeatures(const pulsetrack_msgs_msg_dds__Features_* m) {
  const dds_sequence_pulsetrack_msgs_msg_dds__Feature_* fs = &m->features;
  uint32_t ok = 0;
  for (uint32_t i = 0; i < fs->_length; ++i)
    if (fs->_buffer[i].status == 0) ++ok;  // Feature.msg STATUS_OK=0
  const pulsetrack_msgs_msg_dds__Feature_* f0 = fs->_length > 0 ? &fs->_buffer[0] : NULL;
  printf("features frame=%" PRIu64, m->frame);
  printStamp(&m->header);
  fputs(" rig=", stdout);
  putToken(m->rig_id);
  printf(" n=%" PRIu32 " ok=%" PRIu32 " first_id=%" PRId32, fs->_length, ok, f0 ? f0->id : -1);
  printf(" x0=%.9g y0=%.9g z0=%.9g", f0 ? f0->position.x : NAN, f0 ? f0->position.y : NAN,
         f0 ? f0->position.z : NAN);
  printf(" status0=%d reason0=%d", f0 ? f0->status : -1, f0 ? f0->reason : -1);
  printf(" lx0=%.9g ly0=%.9g rx0=%.9g ry0=%.9g", f0 ? (double)f0->left_x : NAN,
         f0 ? (double)f0->left_y : NAN, f0 ? (double)f0->right_x : NAN,
         f0 ? (double)f0->right_y : NAN);
  // The ok features' left pixels' bounding box (nan without one).
  double box[4] = {INFINITY, INFINITY, -INFINITY, -INFINITY};
  for (uint32_t i = 0; i < fs->_length; ++i) {
    const pulsetrack_msgs_msg_dds__Feature_* f = &fs->_buffer[i];
    if (f->status != 0) continue;
    const double x = f->left_x, y = f->left_y;
    if (x < box[0]) box[0] = x;
    if (y < box[1]) box[1] = y;
    if (x > box[2]) box[2] = x;
    if (y > box[3]) box[3] = y;
  }
  if (ok == 0) box[0] = box[1] = box[2] = box[3] = NAN;
  printf(" lxmin=%.9g lymin=%.9g lxmax=%.9g lymax=%.9g", box[0], box[1], box[2], box[3]);
  fputs(" frame_id=", stdout);
  putToken(m->header.frame_id);
  putchar('\n');
}

static void printDeformation(const pulsetrack_msgs_msg_dds__Deformation_* m) {
  printf("deformation frame=%" PRIu64, m->frame);
  printStamp(&m->header);
  fputs(" rig=", stdout);
  putToken(m->rig_id);
  printf(" dx=%.17g dy=%.17g dz=%.17g", m->displacement.x, m->displacement.y, m->displacement.z);
  printf(" vx=%.17g vy=%.17g vz=%.17g", m->velocity.x, m->velocity.y, m->velocity.z);
  printf(" ok=%" PRIu32 " total=%" PRIu32, m->features_ok, m->features_total);
  printf(" cx=%.17g cy=%.17g cz=%.17g", m->centroid.x, m->centroid.y, m->centroid.z);
  printf(" velocity_delay=%.17g displacement_sigma=%.17g velocity_sigma=%.17g", m->velocity_delay,
         m->displacement_sigma, m->velocity_sigma);
  printf(" detections=%" PRIu32 " continuous=%d", m->detections, m->continuous ? 1 : 0);
  printf(" np=%" PRIu32 " np_displacement=%" PRIu32 " np_sigma=%" PRIu32 " np_model=%" PRIu32,
         m->prediction_horizon._length, m->predicted_displacement._length,
         m->prediction_sigma._length, m->predicted_by_model._length);
  for (uint32_t k = 0; k < m->prediction_horizon._length && k < m->predicted_displacement._length &&
                       k < m->prediction_sigma._length && k < m->predicted_by_model._length;
       ++k) {
    const geometry_msgs_msg_dds__Vector3_* p = &m->predicted_displacement._buffer[k];
    printf(" ph%" PRIu32 "=%.17g pdx%" PRIu32 "=%.17g pdy%" PRIu32 "=%.17g pdz%" PRIu32
           "=%.17g ps%" PRIu32 "=%.17g pm%" PRIu32 "=%d",
           k, m->prediction_horizon._buffer[k], k, p->x, k, p->y, k, p->z, k,
           m->prediction_sigma._buffer[k], k, m->predicted_by_model._buffer[k] ? 1 : 0);
  }
  fputs(" frame_id=", stdout);
  putToken(m->header.frame_id);
  putchar('\n');
}

// A JPEG's size as a decoder finds it: the first SOFn marker's height and width (ITU T.81 B.2.2),
// walking the marker segments from SOI. 0 x 0 when there is none.
static void jpegSize(const uint8_t* d, uint32_t n, uint32_t* w, uint32_t* h) {
  *w = *h = 0;
  if (n < 4 || d[0] != 0xFF || d[1] != 0xD8) return;
  uint32_t i = 2;
  while (i + 4 <= n) {
    if (d[i] != 0xFF) return;
    const uint8_t marker = d[i + 1];
    const uint32_t len = ((uint32_t)d[i + 2] << 8) | d[i + 3];
    const bool sof =
        marker >= 0xC0 && marker <= 0xCF && marker != 0xC4 && marker != 0xC8 && marker != 0xCC;
    if (sof && i + 9 <= n) {
      *h = ((uint32_t)d[i + 5] << 8) | d[i + 6];
      *w = ((uint32_t)d[i + 7] << 8) | d[i + 8];
      return;
    }
    i += 2 + len;
  }
}

static void printImage(const char* side, const sensor_msgs_msg_dds__CompressedImage_* m) {
  printf("image side=%s", side);
  printStamp(&m->header);
  fputs(" format=", stdout);
  putQuoted(m->format);
  const uint8_t* d = m->data._buffer;
  const uint32_t n = m->data._length;
  const bool jpeg = n >= 4 && d[0] == 0xFF && d[1] == 0xD8 && d[n - 2] == 0xFF && d[n - 1] == 0xD9;
  uint32_t w = 0, h = 0;
  jpegSize(d, n, &w, &h);
  printf(" bytes=%" PRIu32 " jpeg=%d width=%" PRIu32 " height=%" PRIu32, n, jpeg ? 1 : 0, w, h);
  fputs(" frame_id=", stdout);
  putToken(m->header.frame_id);
  putchar('\n');
}

static void printHealth(const pulsetrack_msgs_msg_dds__Health_* m) {
  fputs("health", stdout);
  printStamp(&m->header);
  fputs(" rig=", stdout);
  putToken(m->rig_id);
  printf(" state=%u state_text=", (unsigned)m->state);
  putQuoted(m->state_text);
  fputs(" last_error=", stdout);
  putQuoted(m->last_error);
  const struct {
    const char* name;
    const char* value;
  } strings[] = {
      {"source", m->source},
      {"source_state", m->source_state},
      {"trigger_state", m->trigger_state},
      {"recorder_state", m->recorder_state},
      {"tracking_state", m->tracking_state},
      {"clock_state", m->clock_state},
      {"security_state", m->security_state},
      {"output_state", m->output_state},
  };
  for (size_t i = 0; i < sizeof strings / sizeof strings[0]; ++i) {
    printf(" %s=", strings[i].name);
    putQuoted(strings[i].value);
  }
  printf(" clock_synchronized=%d fps=%.9g", m->clock_synchronized ? 1 : 0, (double)m->fps);
  printf(" frames=%" PRIu64 " drops=%" PRIu64 " deadline_misses=%" PRIu64 " unpaired=%" PRIu64
         " missing_triggers=%" PRIu64 " source_faults=%" PRIu64 " recorder_faults=%" PRIu64
         " commands_accepted=%" PRIu64 " commands_refused=%" PRIu64,
         m->frames, m->drops, m->deadline_misses, m->unpaired, m->missing_triggers,
         m->source_faults, m->recorder_faults, m->commands_accepted, m->commands_refused);
  printf(" image_width=%" PRIu32 " image_height=%" PRIu32, m->image_width, m->image_height);
  // stages="capture:p50/p99/max,track:...", microseconds
  fputs(" stages=\"", stdout);
  for (uint32_t i = 0; i < m->stages._length; ++i) {
    const pulsetrack_msgs_msg_dds__StageLatency_* s = &m->stages._buffer[i];
    if (i > 0) putchar(',');
    for (const unsigned char* p = (const unsigned char*)(s->stage ? s->stage : ""); *p; ++p)
      putchar(*p > 0x20 && *p < 0x7f && *p != '"' && *p != '\\' && *p != ',' ? *p : '_');
    printf(":%" PRIu32 "/%" PRIu32 "/%" PRIu32, s->p50_us, s->p99_us, s->max_us);
  }
  putchar('"');
  fputs(" frame_id=", stdout);
  putToken(m->header.frame_id);
  putchar('\n');
}

// One channel of a point: found by name in the cloud's `fields`, read at its declared offset
// with its declared datatype and byte order (PointField.msg: INT8 1 ... FLOAT32 7, FLOAT64 8).
static bool readChannel(const sensor_msgs_msg_dds__PointCloud2_* m, const char* name,
                        uint32_t point, double* out) {
  for (uint32_t i = 0; i < m->fields._length; ++i) {
    const sensor_msgs_msg_dds__PointField_* f = &m->fields._buffer[i];
    if (f->name == NULL || strcmp(f->name, name) != 0) continue;
    const size_t size = f->datatype == 7 ? 4 : f->datatype == 8 ? 8 : 0;
    const size_t at = (size_t)point * m->point_step + f->offset;
    if (size == 0 || f->offset + size > m->point_step || at + size > m->data._length) return false;
    unsigned char b[8];
    memcpy(b, m->data._buffer + at, size);
    const uint16_t probe = 1;
    const bool host_big = *(const unsigned char*)&probe == 0;
    if ((m->is_bigendian != 0) != host_big) {
      for (size_t k = 0; k < size / 2; ++k) {
        const unsigned char c = b[k];
        b[k] = b[size - 1 - k];
        b[size - 1 - k] = c;
      }
    }
    if (size == 4) {
      float v;
      memcpy(&v, b, 4);
      *out = v;
    } else {
      memcpy(out, b, 8);
    }
    return true;
  }
  return false;
}

static void printTracked(const pulsetrack_msgs_msg_dds__TrackedTargets_* m) {
  printf("tracked frame=%" PRIu64, m->frame);
  printStamp(&m->header);
  fputs(" rig=", stdout);
  putToken(m->rig_id);
  printf(" set_id=%" PRIu32 " signal=%" PRIu32 " n=%" PRIu32 " n_position=%" PRIu32
         " n_displacement=%" PRIu32 " n_confidence=%" PRIu32,
         m->set_id, m->signal, m->reference._length, m->position._length, m->displacement._length,
         m->confidence._length);
  for (uint32_t k = 0; k < m->reference._length && k < m->position._length &&
                       k < m->displacement._length && k < m->confidence._length;
       ++k) {
    const geometry_msgs_msg_dds__Point_* r = &m->reference._buffer[k];
    const geometry_msgs_msg_dds__Point_* p = &m->position._buffer[k];
    const geometry_msgs_msg_dds__Vector3_* d = &m->displacement._buffer[k];
    printf(" r%" PRIu32 "x=%.17g r%" PRIu32 "y=%.17g r%" PRIu32 "z=%.17g", k, r->x, k, r->y, k,
           r->z);
    printf(" p%" PRIu32 "x=%.17g p%" PRIu32 "y=%.17g p%" PRIu32 "z=%.17g", k, p->x, k, p->y, k,
           p->z);
    printf(" d%" PRIu32 "x=%.17g d%" PRIu32 "y=%.17g d%" PRIu32 "z=%.17g", k, d->x, k, d->y, k,
           d->z);
    printf(" c%" PRIu32 "=%.9g", k, (double)m->confidence._buffer[k]);
  }
  fputs(" frame_id=", stdout);
  putToken(m->header.frame_id);
  putchar('\n');
}

// "x,y,z;x,y,z" (m) into points; false on a malformed list.
static bool parsePoints(const char* s, geometry_msgs_msg_dds__Point_* out, uint32_t max,
                        uint32_t* n) {
  *n = 0;
  const char* p = s;
  while (*p != '\0') {
    if (*n >= max) return false;
    double v[3];
    for (int i = 0; i < 3; ++i) {
      char* end = NULL;
      errno = 0;
      v[i] = strtod(p, &end);
      if (end == p || errno != 0 || !isfinite(v[i])) return false;
      p = end;
      if (i < 2) {
        if (*p != ',') return false;
        ++p;
      }
    }
    out[*n].x = v[0];
    out[*n].y = v[1];
    out[*n].z = v[2];
    ++*n;
    if (*p == ';') {
      ++p;
      if (*p == '\0') return false;
    } else if (*p != '\0') {
      return false;
    }
  }
  return *n > 0;
}

static void printField(const sensor_msgs_msg_dds__PointCloud2_* m) {
  fputs("field", stdout);
  printStamp(&m->header);
  printf(" width=%" PRIu32 " height=%" PRIu32 " point_step=%" PRIu32 " row_step=%" PRIu32
         " bytes=%" PRIu32 " is_bigendian=%d is_dense=%d",
         m->width, m->height, m->point_step, m->row_step, m->data._length, m->is_bigendian ? 1 : 0,
         m->is_dense ? 1 : 0);
  fputs(" fields=\"", stdout);
  for (uint32_t i = 0; i < m->fields._length; ++i) {
    const sensor_msgs_msg_dds__PointField_* f = &m->fields._buffer[i];
    printf("%s%s:%" PRIu32 ":%u:%" PRIu32, i > 0 ? "," : "", f->name ? f->name : "", f->offset,
           (unsigned)f->datatype, f->count);
  }
  putchar('"');
  static const char* const kNames[7] = {"x", "y", "z", "dx", "dy", "dz", "confidence"};
  const uint32_t points = m->width * m->height;
  double sum[7] = {0}, mid[7] = {NAN, NAN, NAN, NAN, NAN, NAN, NAN};
  double min_z = INFINITY, max_z = -INFINITY;
  uint32_t valid = 0;
  char missing[128] = "";
  for (int c = 0; c < 7; ++c) {
    double v;
    if (points == 0 || !readChannel(m, kNames[c], 0, &v)) {
      strncat(missing, kNames[c], sizeof missing - strlen(missing) - 2);
      strcat(missing, ",");
    }
  }
  for (uint32_t p = 0; p < points && missing[0] == '\0'; ++p) {
    double v[7];
    for (int c = 0; c < 7; ++c) (void)readChannel(m, kNames[c], p, &v[c]);
    if (p == (m->height / 2) * m->width + m->width / 2) memcpy(mid, v, sizeof v);
    if (!isfinite(v[0]) || !isfinite(v[1]) || !isfinite(v[2])) continue;
    ++valid;
    for (int c = 0; c < 7; ++c) sum[c] += v[c];
    if (v[2] < min_z) min_z = v[2];
    if (v[2] > max_z) max_z = v[2];
  }
  const double n = valid > 0 ? (double)valid : (double)NAN;
  printf(" points=%" PRIu32 " valid=%" PRIu32
         " mean_dx=%.9g mean_dy=%.9g mean_dz=%.9g"
         " mean_confidence=%.9g min_z=%.9g max_z=%.9g",
         points, valid, sum[3] / n, sum[4] / n, sum[5] / n, sum[6] / n, min_z, max_z);
  // Every other declared channel (the predictions dx_100ms, ...): its mean over the valid points.
  for (uint32_t i = 0; i < m->fields._length && missing[0] == '\0'; ++i) {
    const char* name = m->fields._buffer[i].name;
    bool known = name == NULL;
    for (int c = 0; c < 7 && !known; ++c) known = strcmp(name, kNames[c]) == 0;
    if (known) continue;
    double total = 0.0;
    for (uint32_t q = 0; q < points; ++q) {
      double x = 0, y = 0, z = 0, v = 0;
      (void)readChannel(m, "x", q, &x);
      (void)readChannel(m, "y", q, &y);
      (void)readChannel(m, "z", q, &z);
      if (!isfinite(x) || !isfinite(y) || !isfinite(z)) continue;
      if (readChannel(m, name, q, &v)) total += v;
    }
    fputs(" mean_", stdout);
    for (const char* c = name; *c; ++c) putchar(*c > 0x20 && *c < 0x7f && *c != '=' ? *c : '_');
    printf("=%.9g", total / n);
  }
  printf(" mx=%.9g my=%.9g mz=%.9g mdx=%.9g mdy=%.9g mdz=%.9g mconf=%.9g", mid[0], mid[1], mid[2],
         mid[3], mid[4], mid[5], mid[6]);
  fputs(" missing=", stdout);
  putQuoted(missing);
  fputs(" frame_id=", stdout);
  putToken(m->header.frame_id);
  putchar('\n');
}

// The reader QoS rmw_cyclonedds_cpp (Humble, rmw_node.cpp create_readwrite_qos) makes of an
// rmw_qos_profile_t with the given history depth, reliability and durability; deadline and
// lifespan unset, liveliness automatic with an infinite lease (the profiles' defaults), local
// publications not ignored (rclcpp's default). Plus the data representation: rmw_cyclonedds's
// sertype allows XCDR1 only, so its readers offer exactly XCDR1.
static dds_qos_t* ros2Qos(int32_t depth, bool reliable, bool transient_local) {
  dds_qos_t* qos = dds_create_qos();
  dds_qset_writer_data_lifecycle(qos, false);  // rmw sets it on readers and writers alike
  dds_qset_history(qos, DDS_HISTORY_KEEP_LAST, depth);
  if (reliable)
    dds_qset_reliability(qos, DDS_RELIABILITY_RELIABLE, DDS_INFINITY);
  else
    dds_qset_reliability(qos, DDS_RELIABILITY_BEST_EFFORT, 0);
  if (transient_local) {
    dds_qset_durability(qos, DDS_DURABILITY_TRANSIENT_LOCAL);
    dds_qset_durability_service(qos, 0, DDS_HISTORY_KEEP_LAST, depth, DDS_LENGTH_UNLIMITED,
                                DDS_LENGTH_UNLIMITED, DDS_LENGTH_UNLIMITED);
  } else {
    dds_qset_durability(qos, DDS_DURABILITY_VOLATILE);
  }
  dds_qset_liveliness(qos, DDS_LIVELINESS_AUTOMATIC, DDS_INFINITY);
  dds_qset_data_representation(qos, 1,
                               (dds_data_representation_id_t[]){DDS_DATA_REPRESENTATION_XCDR1});
  return qos;
}

static dds_entity_t g_participant = 0;

static int fail(const char* what, const char* topic, dds_return_t rc) {
  fprintf(stderr, "ros2_subscriber: %s%s%s: %s\n", what, topic ? " " : "", topic ? topic : "",
          dds_strretcode(rc));
  if (g_participant > 0) dds_delete(g_participant);
  return 2;
}

// A writer on `topic` with `qos` (deleted here), once a reader has matched it (a reliable
// volatile sample written before that is not delivered). 0, or the exit code (named on stderr).
static int matchedWriter(dds_entity_t pp, const dds_topic_descriptor_t* desc, const char* topic,
                         dds_qos_t* qos, int64_t until, dds_entity_t* out) {
  const dds_entity_t tp = dds_create_topic(pp, desc, topic, NULL, NULL);
  if (tp < 0) {
    dds_delete_qos(qos);
    return fail("cannot create the topic", topic, tp);
  }
  const dds_entity_t w = dds_create_writer(pp, tp, qos, NULL);
  dds_delete_qos(qos);
  if (w < 0) return fail("cannot create a writer on", topic, w);
  dds_publication_matched_status_t m;
  memset(&m, 0, sizeof m);
  while (!g_stop && monotonicNs() < until &&
         (dds_get_publication_matched_status(w, &m) != DDS_RETCODE_OK || m.current_count == 0))
    dds_sleepfor(DDS_MSECS(10));
  if (m.current_count == 0) {
    fprintf(stderr, "ros2_subscriber: no reader matched on %s\n", topic);
    return 1;
  }
  *out = w;
  return 0;
}

int main(int argc, char** argv) {
  uint32_t domain = UINT32_MAX;
  const char* ns = "";
  uint32_t want[kTopics] = {1, 1, 1, 0, 0, 0, 0};
  const char* targets_text = NULL;  // --targets: publish one Targets set first
  uint8_t targets_frame = 0;
  uint32_t set_id = 42;
  double timeout_s = 30.0;
  const char* command = NULL;  // --command: publish one Command as a ROS 2 node would
  for (int i = 1; i < argc; ++i) {
    const char* a = argv[i];
    if (strcmp(a, "--help") == 0 || strcmp(a, "-h") == 0) {
      usage(stdout);
      return 0;
    }
    const char* v = i + 1 < argc ? argv[i + 1] : NULL;
    bool ok = v != NULL;
    if (strcmp(a, "--domain") == 0)
      ok = ok && parseU32(v, 232, &domain);
    else if (strcmp(a, "--namespace") == 0)
      ns = v ? v : "";
    else if (strcmp(a, "--features") == 0)
      ok = ok && parseU32(v, 1000000000u, &want[kFeatures]);
    else if (strcmp(a, "--deformation") == 0)
      ok = ok && parseU32(v, 1000000000u, &want[kDeformation]);
    else if (strcmp(a, "--health") == 0)
      ok = ok && parseU32(v, 1000000000u, &want[kHealth]);
    else if (strcmp(a, "--field") == 0)
      ok = ok && parseU32(v, 1000000000u, &want[kField]);
    else if (strcmp(a, "--tracked") == 0)
      ok = ok && parseU32(v, 1000000000u, &want[kTracked]);
    else if (strcmp(a, "--images") == 0) {
      ok = ok && parseU32(v, 1000000000u, &want[kImageLeft]);
      want[kImageRight] = want[kImageLeft];
    } else if (strcmp(a, "--targets") == 0)
      targets_text = v;
    else if (strcmp(a, "--set-id") == 0)
      ok = ok && parseU32(v, 0xffffffffu, &set_id);
    else if (strcmp(a, "--targets-frame") == 0) {
      ok = ok && (strcmp(v, "reference") == 0 || strcmp(v, "latest") == 0);
      if (ok) targets_frame = strcmp(v, "latest") == 0 ? 1 : 0;
    } else if (strcmp(a, "--timeout") == 0)
      ok = ok && parseSeconds(v, &timeout_s);
    else if (strcmp(a, "--command") == 0)
      command = v;
    else {
      fprintf(stderr, "ros2_subscriber: unknown argument '%s'\n", a);
      usage(stderr);
      return 2;
    }
    if (!ok) {
      fprintf(stderr, "ros2_subscriber: %s needs %s, not '%s'\n", a,
              strcmp(a, "--domain") == 0          ? "a domain id 0-232"
              : strcmp(a, "--timeout") == 0       ? "a number of seconds > 0"
              : strcmp(a, "--namespace") == 0     ? "a namespace"
              : strcmp(a, "--targets-frame") == 0 ? "reference or latest"
              : strcmp(a, "--targets") == 0       ? "x,y,z;x,y,z (m)"
                                                  : "a count >= 0",
              v ? v : "(nothing)");
      return 2;
    }
    ++i;
  }
  if (domain == UINT32_MAX) {
    fprintf(stderr, "ros2_subscriber: --domain is required\n");
    usage(stderr);
    return 2;
  }
  if (ns[0] == '/') ++ns;
  if (ns[0] != '\0' && !validNamespace(ns)) {
    fprintf(stderr,
            "ros2_subscriber: namespace '%s' is not a ROS 2 namespace (segments of letters, "
            "digits and '_' separated by '/', none starting with a digit)\n",
            ns);
    return 2;
  }

  char topic[kTopics][256];
  for (int t = 0; t < kTopics; ++t) {
    const int n =
        snprintf(topic[t], sizeof topic[t], "rt/%s%spulsetrack/%s", ns, ns[0] ? "/" : "", kLeaf[t]);
    if (n < 0 || (size_t)n >= sizeof topic[t]) {
      fprintf(stderr, "ros2_subscriber: namespace '%s' is too long\n", ns);
      return 2;
    }
  }

  struct sigaction sa;
  memset(&sa, 0, sizeof sa);
  sa.sa_handler = onSignal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, NULL);
  sigaction(SIGTERM, &sa, NULL);

  // NULL QoS and config: CYCLONEDDS_URI from the environment applies, as for a ROS 2 node.
  const dds_entity_t pp = dds_create_participant(domain, NULL, NULL);
  if (pp < 0) return fail("cannot join the domain (check CYCLONEDDS_URI)", NULL, pp);
  g_participant = pp;

  const dds_topic_descriptor_t* desc[kTopics] = {
      &pulsetrack_msgs_msg_dds__Features__desc,       &pulsetrack_msgs_msg_dds__Deformation__desc,
      &pulsetrack_msgs_msg_dds__Health__desc,         &sensor_msgs_msg_dds__PointCloud2__desc,
      &pulsetrack_msgs_msg_dds__TrackedTargets__desc, &sensor_msgs_msg_dds__CompressedImage__desc,
      &sensor_msgs_msg_dds__CompressedImage__desc};
  // features, deformation: rclcpp::SensorDataQoS() = rmw_qos_profile_sensor_data (best effort,
  // keep last 5, volatile). health: rmw_qos_profile_default made keep last 1 and transient
  // local, i.e. rclcpp::QoS(1).reliable().transient_local(): what a ROS 2 node that wants the
  // latched health value (the daemon's last one, also when it joins late) subscribes with.
  // field: SensorDataQoS too (rviz2's PointCloud2 display's default is reliable; a reliable
  // reader does not match a best-effort writer, so rviz2 is set to best effort: docs/ros2.md).
  dds_entity_t reader[kTopics];
  const dds_entity_t ws = dds_create_waitset(pp);
  if (ws < 0) return fail("cannot create a waitset", NULL, ws);
  for (int t = 0; t < kTopics; ++t) {
    reader[t] = 0;
    // field and targets_tracked only when asked (a role may not read them)
    if ((t == kField || t == kTracked || t == kImageLeft || t == kImageRight) && want[t] == 0)
      continue;
    const dds_entity_t tp = dds_create_topic(pp, desc[t], topic[t], NULL, NULL);
    if (tp < 0) return fail("cannot create the topic", topic[t], tp);
    dds_qos_t* qos = t == kHealth ? ros2Qos(1, true, true) : ros2Qos(5, false, false);
    reader[t] = dds_create_reader(pp, tp, qos, NULL);
    dds_delete_qos(qos);
    if (reader[t] < 0) return fail("cannot create a reader on", topic[t], reader[t]);
    const dds_entity_t cond = dds_create_readcondition(reader[t], DDS_ANY_STATE);
    if (cond < 0) return fail("cannot create a read condition on", topic[t], cond);
    const dds_return_t rc = dds_waitset_attach(ws, cond, t);
    if (rc != DDS_RETCODE_OK) return fail("cannot wait on", topic[t], rc);
  }

  // --command WORD: one pulsetrack_msgs/Command on rt/[NS/]pulsetrack/command, as a ROS 2 node
  // publishes it with rclcpp::QoS(10).reliable() (volatile), after the daemon's reader matched.
  // set_roi carries an ROI outside any image (1300,1000 100x100), which the daemon must refuse
  // on health: "command 77 'set_roi' refused: ...".
  if (command != NULL) {
    char ctopic[256];
    snprintf(ctopic, sizeof ctopic, "rt/%s%spulsetrack/command", ns, ns[0] ? "/" : "");
    const int64_t until = monotonicNs() + (int64_t)(timeout_s * 1e9);
    dds_entity_t w = 0;
    const int rc_w = matchedWriter(pp, &pulsetrack_msgs_msg_dds__Command__desc, ctopic,
                                   ros2Qos(10, true, false), until, &w);
    if (rc_w != 0) return rc_w;
    pulsetrack_msgs_msg_dds__Command_ c;
    memset(&c, 0, sizeof c);
    c.rig_id = (char*)"";
    c.request_id = 77;
    c.command = (char*)command;
    const int32_t roi[4] = {1300, 1000, 100, 100};
    memcpy(c.roi_left, roi, sizeof roi);
    memcpy(c.roi_right, roi, sizeof roi);
    c.depth_tolerance_m = 0.02;
    const dds_return_t rc = dds_write(w, &c);
    if (rc != DDS_RETCODE_OK) return fail("cannot write on", ctopic, rc);
    if (dds_wait_for_acks(w, DDS_SECS(5)) != DDS_RETCODE_OK)
      fprintf(stderr, "ros2_subscriber: the command on %s was not acknowledged\n", ctopic);
    printf("command sent request=77 command=%s topic=%s\n", command, ctopic);
    fflush(stdout);
  }

  // --targets: one Targets set, as a ROS 2 node publishes a setting it wants kept:
  // rclcpp::QoS(1).reliable().transient_local(), after the daemon's reader matched.
  if (targets_text != NULL) {
    char ttopic[256];
    snprintf(ttopic, sizeof ttopic, "rt/%s%spulsetrack/targets", ns, ns[0] ? "/" : "");
    static geometry_msgs_msg_dds__Point_ points[300];
    uint32_t n = 0;
    if (!parsePoints(targets_text, points, 300, &n)) {
      fprintf(stderr, "ros2_subscriber: --targets '%s': expected x,y,z;x,y,z (m)\n", targets_text);
      return 2;
    }
    const int64_t until = monotonicNs() + (int64_t)(timeout_s * 1e9);
    dds_entity_t w = 0;
    const int rc_w = matchedWriter(pp, &pulsetrack_msgs_msg_dds__Targets__desc, ttopic,
                                   ros2Qos(1, true, true), until, &w);
    if (rc_w != 0) return rc_w;
    // The answers' reader first matched to the daemon's writer (best effort: a writer sends
    // only to readers it knows), so that the first answer is not missed.
    if (reader[kTracked] > 0) {
      dds_subscription_matched_status_t sm;
      memset(&sm, 0, sizeof sm);
      while (!g_stop && monotonicNs() < until &&
             (dds_get_subscription_matched_status(reader[kTracked], &sm) != DDS_RETCODE_OK ||
              sm.current_count == 0))
        dds_sleepfor(DDS_MSECS(10));
      dds_sleepfor(DDS_MSECS(200));  // and the daemon's side of the match
    }
    pulsetrack_msgs_msg_dds__Targets_ tg;
    memset(&tg, 0, sizeof tg);
    tg.header.frame_id = (char*)"pulsetrack_left_camera";
    tg.rig_id = (char*)"";
    tg.set_id = set_id;
    tg.frame = targets_frame;
    tg.points._buffer = points;
    tg.points._length = tg.points._maximum = n;
    tg.points._release = false;
    const dds_return_t rc = dds_write(w, &tg);
    if (rc != DDS_RETCODE_OK) return fail("cannot write on", ttopic, rc);
    if (dds_wait_for_acks(w, DDS_SECS(5)) != DDS_RETCODE_OK)
      fprintf(stderr, "ros2_subscriber: the targets on %s were not acknowledged\n", ttopic);
    printf("targets sent set_id=%" PRIu32 " n=%" PRIu32 " frame=%u topic=%s\n", set_id, n,
           (unsigned)targets_frame, ttopic);
    fflush(stdout);
  }

  uint32_t got[kTopics] = {0, 0, 0, 0, 0};
  const int64_t deadline = monotonicNs() + (int64_t)(timeout_s * 1e9);
  bool done = false;
  while (!g_stop) {
    for (int t = 0; t < kTopics; ++t) {
      if (reader[t] == 0) continue;
      for (;;) {
        void* buf[16] = {NULL};  // NULL: Cyclone lends the samples
        dds_sample_info_t info[16];
        const dds_return_t n = dds_take(reader[t], buf, info, 16, 16);
        if (n < 0) return fail("cannot take from", topic[t], n);
        for (dds_return_t i = 0; i < n; ++i) {
          if (!info[i].valid_data) continue;
          if (t == kFeatures)
            printFeatures(buf[i]);
          else if (t == kDeformation)
            printDeformation(buf[i]);
          else if (t == kHealth)
            printHealth(buf[i]);
          else if (t == kField)
            printField(buf[i]);
          else if (t == kTracked)
            printTracked(buf[i]);
          else
            printImage(t == kImageLeft ? "left" : "right", buf[i]);
          fflush(stdout);
          ++got[t];
        }
        if (n > 0) dds_return_loan(reader[t], buf, n);
        if (n < 16) break;
      }
    }
    done = got[kFeatures] >= want[kFeatures] && got[kDeformation] >= want[kDeformation] &&
           got[kHealth] >= want[kHealth] && got[kField] >= want[kField] &&
           got[kTracked] >= want[kTracked] && got[kImageLeft] >= want[kImageLeft] &&
           got[kImageRight] >= want[kImageRight];
    if (done) break;
    const int64_t left = deadline - monotonicNs();
    if (left <= 0) break;
    const dds_return_t rc =
        dds_waitset_wait(ws, NULL, 0, left < DDS_MSECS(200) ? left : DDS_MSECS(200));
    if (rc < 0) return fail("cannot wait", NULL, rc);
  }

  printf("summary features=%" PRIu32 " deformation=%" PRIu32 " health=%" PRIu32 " field=%" PRIu32
         " tracked=%" PRIu32 " images=%" PRIu32 "/%" PRIu32 "\n",
         got[kFeatures], got[kDeformation], got[kHealth], got[kField], got[kTracked],
         got[kImageLeft], got[kImageRight]);
  fflush(stdout);
  if (!done) {
    fprintf(stderr, "ros2_subscriber: %s after %.3g s:", g_stop ? "interrupted" : "timeout",
            timeout_s);
    for (int t = 0; t < kTopics; ++t) {
      if (reader[t] == 0) continue;
      dds_subscription_matched_status_t m;
      dds_requested_incompatible_qos_status_t q;
      const bool have_m = dds_get_subscription_matched_status(reader[t], &m) == DDS_RETCODE_OK;
      const bool have_q =
          dds_get_requested_incompatible_qos_status(reader[t], &q) == DDS_RETCODE_OK;
      fprintf(stderr, " %s %" PRIu32 "/%" PRIu32 " (matched writers %" PRIu32, topic[t], got[t],
              want[t], have_m ? m.current_count : 0);
      if (have_q && q.total_count > 0)
        fprintf(stderr, ", %" PRIu32 " with incompatible QoS, last policy id %" PRIu32,
                q.total_count, (uint32_t)q.last_policy_id);
      fputs(")", stderr);
    }
    fputs("\n", stderr);
  }
  dds_delete(pp);
  return done ? 0 : 1;
}
