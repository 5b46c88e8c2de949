#!/usr/bin/env python3
"""Writes the fuzz harnesses' seed corpora (fuzz/corpus/<harness>/) from the documented formats
(docs/recording-format.md, docs/trigger-box.md, docs/validation.md) and the repo's shipped files,
independently of the C++ writers. Run from the repo root; the output is committed."""
import os, shutil, struct, zlib

root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
out = os.path.join(root, "fuzz", "corpus")


def put(harness, name, data):
    d = os.path.join(out, harness)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, name), "wb") as f:
        f.write(data if isinstance(data, bytes) else data.encode())


def text(path):
    with open(os.path.join(root, path), "rb") as f:
        return f.read()


# Rig: the shipped rig, and the small one fuzz_recording's folder uses.
put("fuzz_rig", "paper-rig.yaml", text("config/rigs/paper-rig.yaml"))
put("fuzz_rig", "nested", b"%YAML:1.0\n---\nzz: " + b"[" * 40 + b"\n")

# frames.ptv for a 16x12 recording (the harness's manifest and rig say 16x12).
W, H = 16, 12
fh = b"PTRKSTR1" + struct.pack("<5I", 1, 32, W, H, 1)
fh += struct.pack("<I", zlib.crc32(fh))


def record(frame, t_ns, codec, left, right):
    h = struct.pack("<IIQQqqIIIII", 0x52465450, 64, frame, 1000 + frame, t_ns, t_ns + 20000, 0,
                    codec, len(left), len(right), zlib.crc32(left + right))
    return h + struct.pack("<I", zlib.crc32(h)) + left + right


img = lambda k: bytes((x * 7 + k * 13) % 256 for x in range(W * H))
put("fuzz_recording", "two-raw-frames",
    fh + record(0, 0, 0, img(0), img(1)) + record(2, 200_000_000, 0, img(2), img(3)))
put("fuzz_recording", "header-only", fh)
put("fuzz_recording", "manifest",
    b"M" + b'format = "pulsetrack-recording"\nversion = 1\nwidth = 16\nheight = 12\n'
    b'pixel_format = "gray8"\nnominal_fps = 10\n')

# Track and deformation CSVs (first byte: 0 track, 1 deformation).
put("fuzz_track_csv", "track",
    b"\x00frame,t,id,xl,yl,xr,yr,x,y,z,ncc,nmi,status\n"
    b"0,0.000000,1,100.0,200.0,80.0,200.0,1.00000,2.00000,300.00000,0.9900,0.8000,ok\n"
    b"1,0.100000,1,100.5,200.1,80.4,200.1,1.01000,2.00000,300.01000,0.9800,0.7900,occluded:glint\n")
put("fuzz_track_csv", "deformation",
    b"\x01frame,t,dx,dy,dz,vx,vy,vz,velocity_delay,displacement_sigma,velocity_sigma,cx,cy,cz,ok,"
    b"total,detections,continuous\n"
    b"0,0.0,0,0,0,0,0,0,0.1,0.00001,0.0001,1,2,300,100,100,1,1\n")

# Reference-tracker inputs (first byte: 0 csv, 1 poses, 2 divots, 3 protocol).
put("fuzz_reference", "ndi-poses",
    b"\x01Frame,t_ns,Q0,Qx,Qy,Qz,Tx,Ty,Tz\n0,0,1,0,0,0,10,20,300\n1,100000000,1,0,0,0,10,20,301\n"
    b"2,200000000,MISSING,,,,,,\n")
put("fuzz_reference", "matrix-poses",
    b"\x01frame,m00,m01,m02,m03,m10,m11,m12,m13,m20,m21,m22,m23\n0,1,0,0,1,0,1,0,2,0,0,1,3\n")
put("fuzz_reference", "divots",
    b"\x02divot,x,y,z\n" + b"".join(b"%d,%d,%d,0\n" % (i, 10 * i, 5 * i) for i in range(1, 9)))
put("fuzz_reference", "protocol",
    b"\x03set,acquisition,first_frame,last_frame,roi_left_x,roi_left_y,roi_left_w,roi_left_h,"
    b"roi_right_x,roi_right_y,roi_right_w,roi_right_h\n0,0,0,9,100,100,200,200,80,100,200,200\n")
put("fuzz_reference", "csv", b"\x00# comment\na,b\n1,2\n")


# Trigger box reports: CRC-8/SMBUS over the bytes before it, 64 bytes in all.
def crc8(data):
    c = 0
    for b in data:
        c ^= b
        for _ in range(8):
            c = ((c << 1) ^ 0x07) & 0xFF if c & 0x80 else (c << 1) & 0xFF
    return c


def report(body):
    return (body + bytes([crc8(body)])).ljust(64, b"\0")


put("fuzz_trigger_report", "pulse", report(b"\x81" + struct.pack("<IQ", 42, 123456789)))
put("fuzz_trigger_report", "status", report(b"\x82" + struct.pack("<BIIHB", 1, 100000, 42, 0x0102, 0)))

# Scenes and the daemon config: the shipped files.
for s in ("cortex-60s", "cortex-hard", "plate-static", "plate-dynamic"):
    put("fuzz_scene", s + ".toml", text("config/scenes/%s.toml" % s))
put("fuzz_daemon_config", "pulsetrackd.toml", text("config/pulsetrackd.toml"))

# Commands: FuzzedDataProvider's layout is its own; a few byte strings to start from.
put("fuzz_command", "set_roi", b"rig-a\\set_roi\\" + bytes(range(64)))
put("fuzz_command", "start", b"\\start\\\x01\x01")
