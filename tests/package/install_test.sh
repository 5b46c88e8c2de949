#!/usr/bin/env bash
# tests/package/install_test.sh DEB: installs the amd64 package into a clean Debian 12 root made
# with mmdebstrap (minbase, bookworm and its updates and security), with apt as a new machine
# would (`apt install ./pulsetrack_*.deb` pulls the dependencies), and checks it as the
# technician meets it: the installed config passes pulsetrackd --check-config, the installed unit
# passes systemd-analyze verify, the user exists in the video group, the state folders exist
# with their modes, udev parses the installed rule, the conffiles are registered, both programs
# run, and removal keeps /var/lib/pulsetrack (recordings are patient data).
# Needs root (mmdebstrap --mode=root and chroot): exits 77 (skipped, loudly) otherwise.
set -euo pipefail
deb=$(realpath "${1:?usage: install_test.sh DEB}")
[[ -f $deb ]] || { echo "install_test: no package at $deb" >&2; exit 1; }
if [[ $(id -u) -ne 0 ]]; then
  echo "install_test: SKIPPED: needs root (mmdebstrap --mode=root, chroot)" >&2
  exit 77
fi
command -v mmdebstrap >/dev/null || { echo "install_test: mmdebstrap missing (scripts/bootstrap)" >&2; exit 1; }

root=$(mktemp -d /var/tmp/pulsetrack-root.XXXXXX)
trap 'rm -rf "$root"' EXIT
check=$(mktemp /var/tmp/pulsetrack-check.XXXXXX)
trap 'rm -rf "$root" "$check"' EXIT

# What runs inside the new root after the install (mmdebstrap mounts /proc, /sys and /dev).
cat > "$check" <<'CHECK'
#!/bin/bash
set -euo pipefail
fail() { echo "install_test: FAIL: $*" >&2; exit 1; }
pass() { echo "install_test: ok: $*"; }

[[ $(dpkg-query -W -f='${Status}' pulsetrack) == "install ok installed" ]] || fail "not installed"
pass "apt installed $(dpkg-query -W -f='${Package} ${Version} ${Architecture}' pulsetrack)"

out=$(pulsetrackd --check-config -c /etc/pulsetrack/pulsetrackd.toml 2>&1) ||
  fail "pulsetrackd --check-config on the installed config: $out"
pass "pulsetrackd --check-config: $(echo "$out" | tail -1)"
# ...and it would have said what is wrong with a broken one.
cp /etc/pulsetrack/pulsetrackd.toml /tmp/bad.toml
sed -i 's/^fps = 30.0/fps = "fast"/' /tmp/bad.toml
if out=$(pulsetrackd --check-config -c /tmp/bad.toml 2>&1); then fail "a bad config passed"; fi
grep -q "bad.toml" <<<"$out" || fail "the bad config's error names no file: $out"
pass "a broken copy is refused: $(echo "$out" | head -1)"

out=$(systemd-analyze verify /lib/systemd/system/pulsetrackd.service 2>&1) ||
  fail "systemd-analyze verify: $out"
[[ -z $out ]] || fail "systemd-analyze verify warned: $out"
pass "systemd-analyze verify pulsetrackd.service: clean"
out=$(systemd-analyze verify /lib/systemd/system/pulsetrack-console.service 2>&1) ||
  fail "systemd-analyze verify pulsetrack-console.service: $out"
[[ -z $out ]] || fail "systemd-analyze verify pulsetrack-console.service warned: $out"
pass "systemd-analyze verify pulsetrack-console.service: clean"

# The console as its unit would start it: the installed page, a certificate and users made with
# the installed tools; it serves the login page over TLS and refuses the API without a login.
ks=/tmp/console-ks
/usr/share/pulsetrack/security/security init "$ks" >/dev/null
/usr/share/pulsetrack/security/security tls "$ks" console >/dev/null
echo "installed-pass-1" | pulsetrack console-user --users /tmp/console-users --user tech >/dev/null
pulsetrack console --port 18443 --cert "$ks/tls/console/cert.pem" --key "$ks/tls/console/key.pem" \
  --users /tmp/console-users --rig /etc/pulsetrack/rigs/paper-rig.yaml >/tmp/console.log 2>&1 &
console=$!
for _ in $(seq 100); do grep -q "console: serving" /tmp/console.log && break; sleep 0.2; done
grep -q "console: serving" /tmp/console.log || fail "the console did not start: $(cat /tmp/console.log)"
page=$(curl -sS --cacert "$ks/tls/console/ca.cert.pem" https://localhost:18443/login.html 2>&1) ||
  fail "the console's page: $page"
page+=" events $(curl -sS -o /dev/null -w '%{http_code}' --cacert "$ks/tls/console/ca.cert.pem" \
  https://localhost:18443/api/events 2>&1)"
kill $console
grep -q "pulsetrack console" <<<"$page" || fail "the login page is not the console's: $page"
grep -q "events 401" <<<"$page" || fail "the API answered without a login: $page"
pass "pulsetrack console serves the installed page over TLS (login page; the API 401 without a login)"

out=$(systemd-analyze verify /lib/systemd/system/pulsetrack-igtl.service 2>&1) ||
  fail "systemd-analyze verify pulsetrack-igtl.service: $out"
[[ -z $out ]] || fail "systemd-analyze verify pulsetrack-igtl.service warned: $out"
# The bridge as its unit would start it (its options from the installed igtl.env), on a port of
# its own; Debian's libopenigtlink came with the package's dependencies.
# (systemd's EnvironmentFile syntax, not a shell's: the value is read, not sourced.)
igtl_args=$(sed -n 's/^PULSETRACK_IGTL_ARGS=//p' /etc/pulsetrack/igtl.env)
[[ -n $igtl_args ]] || fail "/etc/pulsetrack/igtl.env sets no PULSETRACK_IGTL_ARGS"
# shellcheck disable=SC2086
pulsetrack igtl ${igtl_args/--port 18944/--port 18945} >/tmp/igtl.log 2>&1 &
igtl=$!
for _ in $(seq 100); do grep -q "igtl: serving" /tmp/igtl.log && break; sleep 0.2; done
grep -q "igtl: serving OpenIGTLink on 127.0.0.1:18945" /tmp/igtl.log ||
  fail "the OpenIGTLink bridge did not start: $(cat /tmp/igtl.log)"
kill $igtl
pass "pulsetrack-igtl.service verifies; pulsetrack igtl serves with the installed igtl.env ($(dpkg-query -W -f='${Package} ${Version}' 'libopenigtlink*' | head -1))"

entry=$(getent passwd pulsetrack) || fail "no user pulsetrack"
[[ $(cut -d: -f6 <<<"$entry") == /var/lib/pulsetrack ]] || fail "home: $entry"
[[ $(cut -d: -f7 <<<"$entry") == */nologin ]] || fail "shell: $entry"
id -nG pulsetrack | tr ' ' '\n' | grep -qx video || fail "pulsetrack is not in video: $(id -nG pulsetrack)"
pass "user: $entry; groups: $(id -nG pulsetrack)"

[[ $(stat -c '%U:%G %a' /var/lib/pulsetrack/recordings) == "pulsetrack:pulsetrack 700" ]] ||
  fail "recordings folder: $(stat -c '%U:%G %a' /var/lib/pulsetrack/recordings)"
pass "tmpfiles: /var/lib/pulsetrack/recordings pulsetrack:pulsetrack 700"

# udev parses every rules file on `udevadm test`; a file it cannot parse is named in its log. A
# broken rule next to ours proves the log would show it.
rules=/lib/udev/rules.d/70-pulsetrack.rules
[[ -f $rules ]] || fail "no $rules"
echo 'SUBSYSTEM=="hidraw", BOGUS{x}=="1", GROUP="video"' > /etc/udev/rules.d/99-broken.rules
said() { grep -F "$1" <<<"$log" | grep -v "Reading rules file" || true; }
log=$(udevadm test /class/mem/null 2>&1 || true)
broken=$(said 99-broken.rules)
[[ -n $broken ]] || fail "udevadm test did not report a broken rule: $log"
rm /etc/udev/rules.d/99-broken.rules
log=$(udevadm test /class/mem/null 2>&1 || true)
grep -q "Reading rules file: .*/70-pulsetrack.rules" <<<"$log" || fail "udev did not read $rules"
[[ -z $(said 70-pulsetrack.rules) ]] || fail "udev complains about $rules: $(said 70-pulsetrack.rules)"
grep -q 'ATTRS{idVendor}=="1209", ATTRS{idProduct}=="7054", GROUP="video"' "$rules" ||
  fail "$rules does not give the trigger box to video"
pass "udev reads $rules without a complaint (a broken rule beside it: $broken)"

conf=$(dpkg-query -W -f='${Conffiles}' pulsetrack)
grep -q "/etc/pulsetrack/pulsetrackd.toml" <<<"$conf" || fail "pulsetrackd.toml is no conffile"
grep -q "/etc/pulsetrack/igtl.env" <<<"$conf" || fail "igtl.env is no conffile"
pass "conffiles: $(awk '{print $1}' <<<"$conf" | tr '\n' ' ')"

pulsetrack --version | grep -q "pulsetrack $(dpkg-query -W -f='${Version}' pulsetrack | cut -d- -f1)" ||
  fail "pulsetrack --version"
pulsetrackd --version >/dev/null || fail "pulsetrackd --version"
[[ -f /usr/share/man/man8/pulsetrackd.8.gz && -f /usr/share/man/man1/pulsetrack.1.gz ]] || fail "man pages"
[[ -f /usr/share/pulsetrack/ros2/pulsetrack_msgs/msg/Health.msg ]] || fail "ROS 2 msg files"
pass "both programs run; man pages, docs and the ROS 2 message package are there"

touch /var/lib/pulsetrack/recordings/case-001
apt-get remove -y -qq pulsetrack >/dev/null
[[ -f /var/lib/pulsetrack/recordings/case-001 ]] || fail "removing the package deleted a recording"
apt-get purge -y -qq pulsetrack >/dev/null
[[ -f /var/lib/pulsetrack/recordings/case-001 ]] || fail "purging the package deleted a recording"
[[ ! -e /etc/pulsetrack/pulsetrackd.toml ]] || fail "purge left the conffile"
pass "remove and purge keep /var/lib/pulsetrack's recordings"
echo "install_test: all checks passed"
CHECK
chmod 755 "$check"

mirror=http://deb.debian.org/debian
security=http://deb.debian.org/debian-security
echo "install_test: a clean Debian 12 root in $root, then apt install ./$(basename "$deb")"
# udev: the rule's check; openssl (scripts/security) and curl: the console's check, as a technician
# would have them.
mmdebstrap --variant=minbase --mode=root --include=udev,openssl,curl \
  --customize-hook="copy-in $deb /root" \
  --customize-hook="copy-in $check /root" \
  --customize-hook="chroot \"\$1\" apt-get install -y -q /root/$(basename "$deb")" \
  --customize-hook="chroot \"\$1\" /root/$(basename "$check")" \
  bookworm "$root" \
  "deb $mirror bookworm main" "deb $mirror bookworm-updates main" \
  "deb $security bookworm-security main"
