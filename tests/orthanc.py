"""A real Orthanc (Debian packages ``orthanc`` + ``orthanc-dicomweb``) for the PACS tests.

:func:`start_orthanc` runs ``/usr/sbin/Orthanc`` with a temporary storage folder, its own free
HTTP port, the DICOMweb plugin, HTTP basic authentication (a random password) and
``RemoteAccessAllowed: false`` (it refuses every client that is not on this machine) plus
``HttpBindAddresses: ["127.0.0.1"]`` (binds loopback only in Orthanc releases since late 2025; Debian's 1.10.1
ignores it and binds every interface, still refusing remote clients); its DICOM port is off (the
tests talk DICOMweb to it).
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
    #: The self-signed certificate (PEM) when the server is reached through :class:`TlsProxy`.
    certificate: Path | None = None

    @property
    def url(self) -> str:
        return f"{'https' if self.certificate else 'http'}://127.0.0.1:{self.http_port}"

    @property
    def dicomweb_url(self) -> str:
        return f"{self.url}/dicom-web"

    def rest(self, path: str, method: str = "GET") -> object:
        """Orthanc's own REST API (for checks the DICOMweb client does not make)."""
        import ssl

        request = urllib.request.Request(self.url + path, method=method)
        token = b64encode(f"{self.username}:{self.password}".encode()).decode()
        request.add_header("Authorization", f"Basic {token}")
        context = ssl.create_default_context(cafile=str(self.certificate)) if self.certificate else None
        with urllib.request.urlopen(request, timeout=10, context=context) as response:
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


def self_signed_certificate(folder: Path) -> tuple[Path, Path]:
    """(certificate, certificate + key) for 127.0.0.1, made with the openssl command."""
    key, cert = folder / "key.pem", folder / "cert.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out", str(cert),
         "-days", "1", "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1"],
        check=True, capture_output=True, timeout=60,
    )  # fmt: skip
    both = folder / "orthanc.pem"
    both.write_text(cert.read_text() + key.read_text())
    both.chmod(0o600)
    return cert, both


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
        "HttpBindAddresses": ["127.0.0.1"],  # releases since late 2025; older ones ignore it (and bind all)
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


class TlsProxy:
    """HTTPS in front of a plain-HTTP server on this machine (TLS ends here, bytes are relayed).

    Orthanc 1.10.1 as packaged by Debian crashes (SIGSEGV) on its first HTTPS connection with
    its own ``SslEnabled``, so the HTTPS tests put this proxy, with a self-signed certificate
    for 127.0.0.1, in front of the plain Orthanc. Listens on 127.0.0.1 only; daemon threads.
    """

    def __init__(self, target_port: int, folder: Path) -> None:
        import ssl
        import threading

        self.certificate, both = self_signed_certificate(folder)
        self.context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        self.context.load_cert_chain(str(both))
        self.target_port = target_port
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = int(self.listener.getsockname()[1])
        self._thread = threading.Thread(target=self._accept, daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        import ssl
        import threading

        while True:
            try:
                raw, _ = self.listener.accept()
            except OSError:
                return  # closed
            try:
                client = self.context.wrap_socket(raw, server_side=True)
            except (ssl.SSLError, OSError):
                raw.close()  # a client that does not trust the certificate hangs up here
                continue
            upstream = socket.create_connection(("127.0.0.1", self.target_port), timeout=30)
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for sock in (src, dst):
                try:
                    sock.close()
                except OSError:
                    pass

    def close(self) -> None:
        self.listener.close()
