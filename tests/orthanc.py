"""A real Orthanc (Debian packages ``orthanc`` + ``orthanc-dicomweb``) for the PACS tests.

:func:`start_orthanc` runs ``/usr/sbin/Orthanc`` with a temporary storage folder, its own free
HTTP port, the DICOMweb plugin, HTTP basic authentication (a random password) and
``RemoteAccessAllowed: false`` (Orthanc 1.10 has no bind-address option: it refuses every
client that is not on this machine); its DICOM port is off (the tests talk DICOMweb to it).
"""

from __future__ import annotations

import json
import secrets
import shutil
import socket
import subprocess
import time
import urllib.error
import urllib.request
from base64 import b64encode
from dataclasses import dataclass
from pathlib import Path

ORTHANC = "Orthanc"
#: Where the Debian package orthanc-dicomweb puts the plugin (the first that exists is used).
PLUGIN_CANDIDATES = (
    "/usr/share/orthanc/plugins/libOrthancDicomWeb.so",
    "/usr/lib/orthanc/libOrthancDicomWeb.so",
)
#: Orthanc answers within a second or two here; 30 s only bounds a broken start.
START_TIMEOUT_S = 30.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def dicomweb_plugin() -> str | None:
    found = [p for p in PLUGIN_CANDIDATES if Path(p).is_file()]
    if not found:
        found = (
            sorted(str(p) for p in Path("/usr/lib/orthanc").glob("libOrthancDicomWeb.so*"))
            if Path("/usr/lib/orthanc").is_dir()
            else []
        )
    return found[0] if found else None


def missing() -> str | None:
    """Why the Orthanc tests cannot run here, or None."""
    if shutil.which(ORTHANC) is None and not Path("/usr/sbin/Orthanc").is_file():
        return "Orthanc is not installed (apt-get install orthanc orthanc-dicomweb; .ci/run does it on CI)"
    if dicomweb_plugin() is None:
        return "the Orthanc DICOMweb plugin is not installed (apt-get install orthanc-dicomweb)"
    return None


@dataclass
class OrthancServer:
    process: subprocess.Popen
    http_port: int
    username: str
    password: str
    folder: Path

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    @property
    def dicomweb_url(self) -> str:
        return f"{self.url}/dicom-web"

    def rest(self, path: str, method: str = "GET") -> object:
        """Orthanc's own REST API (for checks the DICOMweb client does not make)."""
        request = urllib.request.Request(self.url + path, method=method)
        token = b64encode(f"{self.username}:{self.password}".encode()).decode()
        request.add_header("Authorization", f"Basic {token}")
        with urllib.request.urlopen(request, timeout=10) as response:
            body = response.read()
        return json.loads(body) if body else None

    def clear(self) -> None:
        """Delete every stored patient (tests start from an empty archive)."""
        for patient in self.rest("/patients"):  # type: ignore[union-attr]
            self.rest(f"/patients/{patient}", method="DELETE")

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=5)


def start_orthanc(folder: Path) -> OrthancServer:
    binary = shutil.which(ORTHANC) or "/usr/sbin/Orthanc"
    plugin = dicomweb_plugin()
    folder.mkdir(parents=True, exist_ok=True)
    storage = folder / "storage"
    storage.mkdir()
    http_port = free_port()
    username, password = "roadmap3d", secrets.token_urlsafe(16)
    config = {
        "Name": "roadmap3d-test",
        "StorageDirectory": str(storage),
        "IndexDirectory": str(storage),
        "HttpPort": http_port,
        "DicomServerEnabled": False,
        "DicomPort": free_port(),
        "RemoteAccessAllowed": False,
        "AuthenticationEnabled": True,
        "RegisteredUsers": {username: password},
        "Plugins": [plugin],
        "DicomWeb": {"Enable": True, "Root": "/dicom-web/"},
        "HttpCompressionEnabled": False,
        "SaveJobs": False,
        "StableAge": 1,
    }
    config_path = folder / "orthanc.json"
    config_path.write_text(json.dumps(config))
    config_path.chmod(0o600)
    logs = folder / "logs"
    logs.mkdir()
    process = subprocess.Popen(
        [binary, f"--logdir={logs}", str(config_path)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        stdin=subprocess.DEVNULL,
    )
    server = OrthancServer(process, http_port, username, password, folder)
    end = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < end:
        if process.poll() is not None:
            raise RuntimeError(f"Orthanc exited with code {process.returncode}; see its logs in {logs}")
        try:
            server.rest("/system")
            plugins = server.rest("/plugins")
            if "dicom-web" not in plugins:  # type: ignore[operator]
                server.stop()
                raise RuntimeError(f"Orthanc started without the DICOMweb plugin ({plugin}); plugins: {plugins}")
            return server
        except (urllib.error.URLError, ConnectionError, OSError):
            time.sleep(0.1)
    server.stop()
    raise RuntimeError(f"Orthanc did not answer on port {http_port} within {START_TIMEOUT_S:.0f} s")
