#pragma once
// Interlaced video (SD endoscope cameras and recorders, 720x576 / 720x480): each frame holds two
// fields exposed half a frame apart, the even rows (top field) and the odd rows (bottom field).
// Tracked as frames, a surface that moves between the fields shows combing, and every template
// straddles two instants. Split into fields, each field becomes a progressive image of the
// frame's full height at its own instant: its rows as they are, the other field's rows
// interpolated from the field's own rows above and below (Catmull-Rom at the half-way point,
// taps -1/16, 9/16, 9/16, -1/16 on the rows 3 and 1 above and 1 and 3 below), so each output
// row keeps its place in the image and the rig's calibration holds unchanged ("bob"
// deinterlacing with a cubic line interpolation).

#include <opencv2/core/mat.hpp>

namespace pulsetrack::vision {

enum class FieldOrder { kTopFirst, kBottomFirst };

// `frame`: an 8-bit single-channel interlaced frame of at least 4 rows. `first` and `second`
// receive the earlier and the later field as full-height images (re-using their buffers when
// they already have the frame's size and type: no allocation then).
void splitFields(const cv::Mat& frame, FieldOrder order, cv::Mat& first, cv::Mat& second);

// One field of `frame` (parity 0: the even rows, 1: the odd rows) as a full-height image.
void fieldImage(const cv::Mat& frame, int parity, cv::Mat& out);

}  // namespace pulsetrack::vision
