#pragma once
// A rig like the paper's (sections 2 and 4.C): two 1360x1024 grey sensors with 4.65 um pixels
// behind 25 mm lenses (f = 5376 px), real radial and tangential distortion, a 60 mm baseline,
// verged so the optical axes cross 450 mm in front of the left camera: both views overlap on a
// 55 mm craniotomy from 40 to 50 cm. config/rigs/paper-rig.yaml is this rig written out.

#include "pulsetrack/vision/stereo_rig.hpp"

namespace pulsetrack::sim {

vision::StereoRig paperRig();

}  // namespace pulsetrack::sim
