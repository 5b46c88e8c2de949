"""What the console's process-level tests share (browser_test.py, security_test.py): DDS kept on
loopback, the failure they raise, and running a setup command. Nothing of the console's own code."""

import subprocess

LOOPBACK = ('<CycloneDDS><Domain id="any"><General><Interfaces><NetworkInterface name="lo"/>'
            '</Interfaces><AllowMulticast>false</AllowMulticast></General><Discovery>'
            '<ParticipantIndex>auto</ParticipantIndex><Peers><Peer Address="127.0.0.1"/></Peers>'
            '</Discovery></Domain></CycloneDDS>')


class Failure(Exception):
    pass


def run(cmd, stdin=None):
    """Runs a setup command; Failure with its output when it fails."""
    r = subprocess.run(cmd, input=stdin, capture_output=True, text=True)
    if r.returncode != 0:
        raise Failure(f"{' '.join(cmd)}: exit {r.returncode}: {r.stdout}{r.stderr}")
    return r.stdout
