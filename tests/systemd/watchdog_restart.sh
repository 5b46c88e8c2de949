#!/usr/bin/env bash
# The shipped unit under a real systemd: systemd 252 runs as PID 1 in private cgroup, mount and
# PID namespaces (recipe: ../shared/design/PLATFORM-NOTES.md), the user comes from the shipped
# sysusers file, the unit is the shipped one with only its paths changed, and the daemon's track
# stage stalls for 5 s after 20 tracked pairs (--stall-track-after). Expected: READY=1 makes the unit
# active, the missing WATCHDOG=1 makes systemd kill it (Result=watchdog) and restart it
# (NRestarts >= 1), as the non-root user with SCHED_FIFO and memory locked. The daemon's output
# goes to the journal (systemd-journald runs in the namespaces, on a tmpfs): its loggers must
# reach it through the journal sink, with priorities and the component named.
# Usage: watchdog_restart.sh PULSETRACKD SOURCE_DIR
# Root only (namespaces, cgroups): skips loudly with exit 77 otherwise.
set -euo pipefail
daemon=$(readlink -f "$1") src=$(readlink -f "$2")
skip() { echo "SKIP: $*"; exit 77; }
[[ $(id -u) == 0 ]] || skip "not root: a real systemd as PID 1 needs namespaces and cgroups"
[[ -x /lib/systemd/systemd ]] || skip "/lib/systemd/systemd is not installed"
command -v unshare >/dev/null || skip "unshare (util-linux) is not installed"
if [[ -d /sys/fs/cgroup/unified ]]; then croot=/sys/fs/cgroup/unified
elif [[ $(stat -fc %T /sys/fs/cgroup) == cgroup2fs ]]; then croot=/sys/fs/cgroup
else skip "no cgroup2 hierarchy"; fi
name=pulsetrack-test-$$
cg=$croot/$name
mkdir "$cg" 2>/dev/null || skip "cannot create a cgroup under $croot"
work=$(mktemp -d)
cleanup() {
  [[ -n ${pid1:-} ]] && kill -KILL "$pid1" 2>/dev/null || true
  wait 2>/dev/null || true
  # The private systemd's cgroups, deepest first.
  find "$cg" -depth -type d -exec rmdir {} \; 2>/dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT

# Cyclone DDS on loopback only, as the other tests (dds::kLoopbackUri).
uri='<CycloneDDS><Domain id="any"><General><Interfaces><NetworkInterface name="lo"/></Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex><Peers><Peer Address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>'
# The shipped config's [realtime] table as it ships, but the stages off the features' path on
# CPU 0: the kernel's view of every thread is checked below.
awk '/^\[realtime\]/ { on = 1; print; next } /^\[/ { on = 0 } on' "$src/config/pulsetrackd.toml" |
  sed 's/^off_path = { priority = 0, cpu = -1 }/off_path = { priority = 0, cpu = 0 }/' >"$work/realtime.toml"
grep -q '^off_path = { priority = 0, cpu = 0 }' "$work/realtime.toml" ||
  { echo "FAIL: the shipped [realtime] table has no 'off_path = { priority = 0, cpu = -1 }' line"; exit 1; }
# Inside the namespaces: a fresh /run and cgroup2, a private copy of the user database, the
# units, then systemd as PID 1.
cat >"$work/inner.sh" <<INNER
#!/usr/bin/env bash
set -euo pipefail
mount --make-rprivate /
mount -t tmpfs tmpfs /run
umount -R /sys/fs/cgroup
mount -t cgroup2 cgroup2 /sys/fs/cgroup
mkdir -p /run/pt/etc-up /run/pt/etc-work /run/pt/bin /run/systemd/system
# /etc writable in this namespace only (sysusers adds the user there).
mount -t overlay overlay -o lowerdir=/etc,upperdir=/run/pt/etc-up,workdir=/run/pt/etc-work /etc
# The journal on a tmpfs: nothing reaches the host's /var/log/journal.
mkdir -p /var/log/journal && mount -t tmpfs tmpfs /var/log/journal
systemd-sysusers "$src/systemd/pulsetrack.sysusers.conf"
cp "$daemon" /run/pt/bin/pulsetrackd
cp -r "$src/config" /run/pt/config
cat >/run/pt/config/test.toml <<TOML
rig_id = "rig-systemd"
[dds]
domain_id = 91
[source]
kind = "sim"
scene = "scenes/cortex-60s.toml"
fps = 10.0
TOML
cat "$work/realtime.toml" >>/run/pt/config/test.toml
sed -e 's|/usr/sbin/pulsetrackd|/run/pt/bin/pulsetrackd|g' \
    -e 's|/etc/pulsetrack/pulsetrackd.toml|/run/pt/config/test.toml|g' \
    -e 's|^ExecStart=\(.*\)|ExecStart=\1 --stall-track-after 20|' \
    -e 's|^\[Service\]|[Service]\nEnvironmentFile=/run/pt/dds.env|' \
    -e 's|^\[Unit\]|[Unit]\nDefaultDependencies=no|' \
    "$src/systemd/pulsetrackd.service" >/run/systemd/system/pulsetrackd.service
cat >/run/pt/dds.env <<'ENV'
CYCLONEDDS_URI='$uri'
ENV
cat >/run/systemd/system/pt-test.target <<UNIT
[Unit]
Description=pulsetrack watchdog test
AllowIsolate=yes
DefaultDependencies=no
Wants=systemd-journald.socket systemd-journald.service pulsetrackd.service
UNIT
export container=pulsetrack-test
exec /lib/systemd/systemd --system --unit=pt-test.target --log-target=console --log-color=no
INNER
chmod +x "$work/inner.sh"

echo $$ >"$cg/cgroup.procs"
unshare --cgroup --mount --pid --fork --mount-proc --kill-child=SIGKILL "$work/inner.sh" \
  >"$work/systemd.log" 2>&1 &
upid=$!
# systemd's PID outside: the child of unshare.
for _ in $(seq 50); do
  pid1=$(pgrep -P "$upid" | head -1 || true)
  [[ -n $pid1 ]] && break
  sleep 0.1
done
[[ -n ${pid1:-} ]] || { cat "$work/systemd.log"; skip "unshare did not start (namespaces refused?)"; }
# Leave our own shell out of systemd's cgroup tree (its root is $cg).
echo $$ >"$croot/cgroup.procs" 2>/dev/null || true
sctl() { nsenter -t "$pid1" -m -p systemctl "$@"; }
up=0
for _ in $(seq 100); do
  if sctl is-system-running >/dev/null 2>&1 || [[ $(sctl is-system-running 2>/dev/null) =~ ^(running|degraded|starting)$ ]]; then up=1; break; fi
  sleep 0.2
done
((up)) || { tail -30 "$work/systemd.log"; skip "systemd did not come up as PID 1 in the namespaces here"; }

show() { sctl show pulsetrackd.service -p "$1" --value 2>/dev/null || true; }
# Up to 90 s: active (READY=1), then a watchdog kill and a restart.
active_pid="" restarts=0 saw_active=0 saw_watchdog=0
for _ in $(seq 450); do
  state=$(show ActiveState)
  if [[ $state == active && -z $active_pid ]]; then active_pid=$(show MainPID); saw_active=1; fi
  [[ $(show Result) == watchdog ]] && saw_watchdog=1
  restarts=$(show NRestarts)
  [[ ${restarts:-0} -ge 1 && $(show ActiveState) == active ]] && break
  sleep 0.2
done
log=$(nsenter -t "$pid1" -m -p journalctl -u pulsetrackd -o cat --no-pager 2>/dev/null || true)
echo "--- journalctl -u pulsetrackd ---"; echo "$log" | tail -20
# The loggers' fields in the journal: the message with its component, priority info (6).
verbose=$(nsenter -t "$pid1" -m -p journalctl -u pulsetrackd -o verbose --no-pager \
  MESSAGE="[pipeline] running, rig rig-systemd, DDS domain 91, topics rt/pulsetrack/features, DDS unsecured" \
  2>/dev/null || true)
new_pid=$(show MainPID)
user=$(nsenter -t "$pid1" -m -p ps -o user= -p "$new_pid" 2>/dev/null || true)
policy=$(nsenter -t "$pid1" -m -p ps -L -o cls= -p "$new_pid" 2>/dev/null | sort -u | tr '\n' ' ' || true)
echo "Result=watchdog seen: $saw_watchdog; first active pid $active_pid, now $new_pid, NRestarts=$restarts, user '$user', scheduling classes: $policy"
fail=0
((saw_active)) || { echo "FAIL: the unit never became active (no READY=1)"; fail=1; }
[[ ${restarts:-0} -ge 1 ]] || { echo "FAIL: no restart after the stall"; fail=1; }
((saw_watchdog)) || { echo "FAIL: systemd never showed Result=watchdog"; fail=1; }
[[ $new_pid != "$active_pid" && $new_pid != 0 ]] || { echo "FAIL: the same process still runs"; fail=1; }
[[ $user == pulsetrack ]] || { echo "FAIL: runs as '$user', not the pulsetrack user"; fail=1; }
[[ $policy == *FF* ]] || { echo "FAIL: no SCHED_FIFO thread (classes: $policy)"; fail=1; }
# Each thread as the kernel sees it (procps and /proc, not the daemon's code): the stages on the
# features' path SCHED_FIFO at the shipped priorities, on any CPU; those off it (field, stereo
# refresh, preview) at normal priority, on CPU 0 as [realtime] off_path says.
threads=$(nsenter -t "$pid1" -m -p ps -L -o tid=,comm=,cls=,rtprio= -p "$new_pid" 2>/dev/null || true)
echo "--- threads ---"; echo "$threads"
all_cpus=$(nsenter -t "$pid1" -m -p awk '/^Cpus_allowed_list/ { print $2 }' /proc/1/status 2>/dev/null || true)
expect_thread() {  # expect_thread NAME CLASS RTPRIO CPUS
  local line tid cls prio cpus
  line=$(awk -v n="$1" '$2 == n' <<<"$threads" | head -1)
  [[ -n $line ]] || { echo "FAIL: no thread named $1"; fail=1; return; }
  read -r tid _ cls prio <<<"$line"
  cpus=$(nsenter -t "$pid1" -m -p awk '/^Cpus_allowed_list/ { print $2 }' "/proc/$new_pid/task/$tid/status" 2>/dev/null || true)
  [[ $cls == "$2" && $prio == "$3" && $cpus == "$4" ]] ||
    { echo "FAIL: thread $1 is $cls priority $prio on CPUs '$cpus', expected $2 $3 on '$4'"; fail=1; }
}
expect_thread pt-capture FF 80 "$all_cpus"
expect_thread pt-track FF 70 "$all_cpus"
expect_thread pt-publish FF 60 "$all_cpus"
expect_thread pt-field TS - 0
expect_thread pt-refresh TS - 0
expect_thread pt-preview TS - 0
grep -q "PRIORITY=6" <<<"$verbose" && grep -q "SYSLOG_IDENTIFIER=pulsetrackd" <<<"$verbose" ||
  { echo "FAIL: the daemon's '[pipeline] running' line is not in the journal with PRIORITY=6 and SYSLOG_IDENTIFIER=pulsetrackd"; echo "$verbose" | head -30; fail=1; }
# The stall's fault is logged as an error (PRIORITY=3), not as information.
nsenter -t "$pid1" -m -p journalctl -u pulsetrackd -p err --no-pager -o cat 2>/dev/null |
  grep -q "^\[pipeline\] state fault" ||
  { echo "FAIL: '[pipeline] state fault' is not in the journal at priority err"; fail=1; }
exit $fail
