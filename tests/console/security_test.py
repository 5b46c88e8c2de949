#!/usr/bin/python3
"""The console as a DDS Security participant: on a secured domain, a console whose enclave has
the `controller` role commands the appliance; one whose enclave is only a `subscriber` shows the
appliance but may not command it, and says why (the page and the API), while the daemon goes on;
one whose enclave is a `monitor` (health only) shows health and says what it may not read.

Real processes: pulsetrackd secured with scripts/security's keystore, three `pulsetrack console`s,
and a plain HTTPS client (urllib, trusting the keystore's CA) reading their Server-Sent Events.
Exit 0 when every check passed, 1 on the first failure (named on stderr).
"""

import argparse
import json
import os
import re
import shutil
import signal
import ssl
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request

from harness import LOOPBACK, Failure, run


class Console:
    """One `pulsetrack console` process and a client logged in to it."""

    def __init__(self, args, tmp, name, enclave, ca, cert, key, users, env):
        self.log_path = os.path.join(tmp, name + ".log")
        self.log = open(self.log_path, "w")
        self.proc = subprocess.Popen(
            [args.cli, "console", "--port", "0", "--cert", cert, "--key", key, "--users", users,
             "--rig", f"{args.source_dir}/config/rigs/paper-rig.yaml", "--www",
             f"{args.source_dir}/console/www", "--domain", str(args.domain), "--enclave",
             enclave], stdout=self.log, stderr=subprocess.STDOUT, env=env)
        self.ctx = ssl.create_default_context(cafile=ca)
        end = time.monotonic() + 30
        self.banner = None
        while time.monotonic() < end and self.banner is None:
            with open(self.log_path) as f:
                self.banner = next((l for l in f.read().splitlines()
                                    if l.startswith("console: serving")), None)
            if self.proc.poll() is not None:
                raise Failure(f"console {name} exited: " + open(self.log_path).read())
            time.sleep(0.2)
        if self.banner is None:
            raise Failure(f"console {name}: no banner in 30 s")
        self.url = "https://localhost:" + re.search(r":(\d+)/", self.banner).group(1)
        status, body, headers = self.request("/api/login", b"user=surgeon&password=correct horse 1")
        if status != 200:
            raise Failure(f"console {name}: login answered {status} {body!r}")
        self.cookie = headers["Set-Cookie"].split(";")[0]
        # One event stream for the console's life, opened before any command is sent, so that
        # no event after it is missed (a stream opened later gets only the latest states).
        req = urllib.request.Request(self.url + "/api/events")
        req.add_header("Cookie", self.cookie)
        self.sse = urllib.request.urlopen(req, context=self.ctx, timeout=10)

    def request(self, path, data=None, json_body=None):
        req = urllib.request.Request(self.url + path, data=data)
        if json_body is not None:
            req.data = json.dumps(json_body).encode()
            req.add_header("Content-Type", "application/json")
        if getattr(self, "cookie", None):
            req.add_header("Cookie", self.cookie)
        try:
            with urllib.request.urlopen(req, context=self.ctx, timeout=10) as r:
                return r.status, r.read(), r.headers
        except urllib.error.HTTPError as e:
            return e.code, e.read(), e.headers

    def events(self, until, timeout=60):
        """Reads the event stream until until(name, data) is true; returns (name, data)."""
        end = time.monotonic() + timeout
        name = None
        while time.monotonic() < end:
            line = self.sse.readline().decode().rstrip("\n")
            if line.startswith("event: "):
                name = line[7:]
            elif line.startswith("data: ") and name:
                data = json.loads(line[6:])
                if until(name, data):
                    return name, data
        raise Failure("the event awaited did not come within %d s" % timeout)

    def close(self):
        self.sse.close()
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
        self.log.close()


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    for a in ("--cli", "--daemon", "--security", "--source-dir"):
        ap.add_argument(a, required=True)
    ap.add_argument("--domain", type=int, default=99)
    args = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="pt-console-sec-")
    env = dict(os.environ, CYCLONEDDS_URI=LOOPBACK)
    daemon = None
    consoles = []
    step = "setting up"
    try:
        ks = os.path.join(tmp, "ks")
        run([args.security, "init", ks])
        run([args.security, "add-participant", ks, "/pulsetrack/daemon", "--role", "daemon"])
        run([args.security, "add-participant", ks, "/pulsetrack/console", "--role", "controller"])
        run([args.security, "add-participant", ks, "/pulsetrack/wall_screen", "--role",
             "subscriber"])
        run([args.security, "add-participant", ks, "/pulsetrack/nurse_display", "--role",
             "monitor"])
        run([args.security, "tls", ks, "console"])
        users = os.path.join(tmp, "users")
        run([args.cli, "console-user", "--users", users, "--user", "surgeon"],
            stdin="correct horse 1\n")
        cfg = os.path.join(tmp, "pulsetrackd.toml")
        with open(cfg, "w") as f:
            f.write(f'''rig_id = "rig-secured"
[dds]
domain_id = {args.domain}
[security]
enclave = "{ks}/enclaves/pulsetrack/daemon"
[source]
kind = "sim"
scene = "{args.source_dir}/config/scenes/cortex-60s.toml"
fps = 10.0
[realtime]
lock_memory = false
capture = {{ priority = 0 }}
track = {{ priority = 0 }}
publish = {{ priority = 0 }}
[health]
period_ms = 200
''')
        dlog = open(os.path.join(tmp, "daemon.log"), "w")
        daemon = subprocess.Popen([args.daemon, "--config", cfg, "--run-for", "300"],
                                  stdout=dlog, stderr=subprocess.STDOUT, env=env)
        tls = os.path.join(ks, "tls/console")
        common = (os.path.join(tls, "ca.cert.pem"), os.path.join(tls, "cert.pem"),
                  os.path.join(tls, "key.pem"), users, env)
        controller = Console(args, tmp, "controller", os.path.join(ks, "enclaves/pulsetrack/console"),
                             *common)
        consoles.append(controller)
        viewer = Console(args, tmp, "wall_screen",
                         os.path.join(ks, "enclaves/pulsetrack/wall_screen"), *common)
        consoles.append(viewer)
        monitor = Console(args, tmp, "nurse_display",
                          os.path.join(ks, "enclaves/pulsetrack/nurse_display"), *common)
        consoles.append(monitor)

        step = "1. the subscriber-role console says it may not command"
        if "may NOT command" not in viewer.banner:
            raise Failure("its banner: " + viewer.banner)
        _, link = viewer.events(lambda n, d: n == "link" and d.get("daemon"))
        if link["may_command"] or not link["command_error"]:
            raise Failure(f"its link event: {link}")
        _, health = viewer.events(lambda n, d: n == "health" and d["state"] == "ok")
        if "secured" not in health["security_state"]:
            raise Failure("the daemon's health: " + health["security_state"])
        status, body, _ = viewer.request("/api/command", json_body={"command": "stop"})
        if status != 403 or b"may not command" not in body:
            raise Failure(f"its stop answered {status} {body!r}")
        print(f"1. subscriber-role console: sees the daemon ({health['security_state']}), its stop "
              f"refused 403: {json.loads(body)['error'][:160]}")

        if link.get("read_denied"):
            raise Failure(f"the subscriber may read everything a console shows: {link}")

        step = "1b. the monitor-role console shows health and says what it may not read"
        _, mlink = monitor.events(lambda n, d: n == "link" and d.get("daemon"))
        denied = mlink.get("read_denied", [])
        want = ["rt/pulsetrack/features", "rt/pulsetrack/deformation", "rt/pulsetrack/field",
                "rt/pulsetrack/left/image/compressed", "rt/pulsetrack/right/image/compressed"]
        if sorted(denied) != sorted(want) or mlink["may_command"]:
            raise Failure(f"its link event: {mlink}")
        if "do not grant reading rt/pulsetrack/features" not in mlink["text"]:
            raise Failure("its link text (the page's banner): " + mlink["text"])
        _, mhealth = monitor.events(lambda n, d: n == "health" and d["state"] == "ok")
        print(f"1b. monitor-role console: health {mhealth['state']}, the banner says: "
              f"{mlink['text'][:200]}")

        step = "2. the controller-role console commands"
        if "may command" not in controller.banner:
            raise Failure("its banner: " + controller.banner)
        controller.events(lambda n, d: n == "health" and d["state"] == "ok")
        status, body, _ = controller.request("/api/command", json_body={"command": "stop"})
        if status != 200:
            raise Failure(f"its stop answered {status} {body!r}")
        controller.events(lambda n, d: n == "command" and d["state"] == "accepted", 30)
        _, h = controller.events(lambda n, d: n == "health" and "stopped" in d["tracking_state"],
                                 30)
        print("2. controller-role console: stop accepted, the daemon's health says: " +
              h["tracking_state"])
        status, _, _ = controller.request("/api/command", json_body={"command": "start"})
        controller.events(lambda n, d: n == "health" and d["tracking_state"].startswith("tracking"),
                          30)
        print("   start accepted, tracking again")
        if daemon.poll() is not None:
            raise Failure("the daemon exited")
        print("PASS")
        return 0
    except Failure as e:
        print(f"FAIL at {step}: {e}", file=sys.stderr)
        for name in ("daemon", "controller", "wall_screen", "nurse_display"):
            p = os.path.join(tmp, name + ".log")
            if os.path.exists(p):
                print(f"--- {name}.log\n" + open(p).read()[-2000:], file=sys.stderr)
        return 1
    finally:
        for c in consoles:
            c.close()
        if daemon is not None:
            daemon.send_signal(signal.SIGTERM)
            try:
                daemon.wait(20)
            except subprocess.TimeoutExpired:
                daemon.kill()
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
