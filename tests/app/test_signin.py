"""Sign-in, origin check and TLS of the web app's server (app/web/signin.py).

A real viser server with the app's guard; clients are a plain HTTP client, a raw websocket
client offering viser's subprotocol (what a script or another web page would do) and, for TLS,
Chromium through Playwright with a self-signed certificate made by openssl.
"""

from __future__ import annotations

import http.client
import shutil
import ssl
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest
import viser
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from app.web import signin
from app.web.main import make_guard, make_server, url_of
from app.web.signin import Guard
from registration.io.passwords import PasswordHash

TOKEN = "sign-in-test-token-42"
SUBPROTOCOL = f"viser-v{viser.__version__}"
CHROMIUM = Path("/usr/bin/chromium")


@pytest.fixture()
def served(tmp_path: Path) -> Iterator[tuple[viser.ViserServer, Guard, list]]:
    audit: list = []
    guard = Guard(TOKEN, audit=lambda action, **f: audit.append((action, f)))
    server = make_server("127.0.0.1", 0, guard=guard)
    yield server, guard, audit
    server.stop()


def get(port: int, path: str, headers: dict[str, str] | None = None) -> http.client.HTTPResponse:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.request("GET", path, headers=headers or {})
    response = conn.getresponse()
    response.read()
    conn.close()
    return response


def sign_in(port: int) -> str:
    """The cookie the server sets for the right token (``name=value``)."""
    response = get(port, f"/?token={TOKEN}")
    assert response.status == 303 and response.getheader("Location") == "/"
    cookie = response.getheader("Set-Cookie")
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie and TOKEN not in cookie
    return cookie.split(";", 1)[0]


def websocket(port: int, **headers: str):
    return connect(f"ws://127.0.0.1:{port}/", subprotocols=[SUBPROTOCOL], additional_headers=headers,
                   open_timeout=10)  # fmt: skip


def test_without_the_token_page_and_websocket_are_refused(served) -> None:
    server, _guard, audit = served
    port = server.get_port()
    assert get(port, "/").status == 401
    assert get(port, "/index.html").status == 401
    assert get(port, "/?token=wrong-token-0000").status == 401
    with pytest.raises(InvalidStatus) as info:
        websocket(port)
    assert info.value.response.status_code == 401
    with pytest.raises(InvalidStatus):
        websocket(port, Cookie="roadmap3d_x=deadbeef")
    actions = [(a, f["result"]) for a, f in audit]
    assert ("sign-in", "refused: wrong token") in actions and ("websocket-refused", "no sign-in") in actions
    assert all(TOKEN not in str(f) for _, f in audit)


def test_with_the_token_the_cookie_lets_page_and_websocket_in(served) -> None:
    server, _guard, _audit = served
    port = server.get_port()
    cookie = sign_in(port)
    page = get(port, "/", {"Cookie": cookie})
    assert page.status == 200
    assert page.getheader("Content-Security-Policy") == "frame-ancestors 'none'"
    assert page.getheader("Referrer-Policy") == "no-referrer"
    own = f"http://127.0.0.1:{port}"
    with websocket(port, Cookie=cookie, Origin=own) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        assert len(ws.recv(timeout=10)) > 0  # the scene's messages flow
    with websocket(port, Cookie=cookie) as ws:  # no Origin: not a browser page
        assert ws.subprotocol == SUBPROTOCOL


def test_a_foreign_origin_is_refused_even_with_the_token(served) -> None:
    server, _guard, audit = served
    port = server.get_port()
    cookie = sign_in(port)
    for origin in ("http://evil.example", f"http://127.0.0.1:{port + 1}", "null"):
        with pytest.raises(InvalidStatus) as info:
            websocket(port, Cookie=cookie, Origin=origin)
        assert info.value.response.status_code == 403
    with pytest.raises(InvalidStatus):
        connect(f"ws://127.0.0.1:{port}/?token={TOKEN}", subprotocols=[SUBPROTOCOL],
                additional_headers={"Origin": "http://evil.example"}, open_timeout=10)  # fmt: skip
    assert ("websocket-refused", "foreign origin") in [(a, f["result"]) for a, f in audit]


def test_allowed_origins_by_flag(tmp_path: Path) -> None:
    guard = Guard(TOKEN, allowed_origins=signin.parse_origins(["https://proxy.example:8443"]))
    server = make_server("127.0.0.1", 0, guard=guard)
    try:
        port = server.get_port()
        cookie = sign_in(port)
        with websocket(port, Cookie=cookie, Origin="https://proxy.example:8443") as ws:
            assert ws.subprotocol == SUBPROTOCOL
        with pytest.raises(InvalidStatus):
            websocket(port, Cookie=cookie, Origin="https://other.example:8443")
    finally:
        server.stop()
    with pytest.raises(ValueError, match="allow-origin"):
        signin.parse_origins(["proxy.example"])


def test_wrong_tokens_are_rate_limited(served) -> None:
    server, _guard, _audit = served
    port = server.get_port()
    for _ in range(signin.MAX_FAILURES):
        assert get(port, "/?token=guess-guess-guess").status == 401
    assert get(port, "/?token=guess-guess-guess").status == 429
    assert get(port, f"/?token={TOKEN}").status == 429  # even the right one, until the window passes


def test_flags(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(signin.ENV_TOKEN, raising=False)
    assert len(make_guard("127.0.0.1").token or "") >= 32  # a random token by default
    assert make_guard("127.0.0.1").token != make_guard("127.0.0.1").token
    monkeypatch.setenv(signin.ENV_TOKEN, "from-the-environment")
    assert make_guard("127.0.0.1").token == "from-the-environment"
    assert make_guard("127.0.0.1", token="from-the-command-line").token == "from-the-command-line"
    with pytest.raises(ValueError, match="at least 12"):
        make_guard("127.0.0.1", token="short")
    assert make_guard("127.0.0.1", no_sign_in=True).token is None
    with pytest.raises(ValueError, match="without sign-in is refused"):
        make_guard("0.0.0.0", no_sign_in=True)
    with pytest.raises(ValueError, match="no such file"):
        make_guard("127.0.0.1", certfile=Path("/nonexistent.pem"))


def test_cli_refuses_an_open_host_without_sign_in(capsys: pytest.CaptureFixture[str]) -> None:
    from app.cli import main

    with pytest.raises(SystemExit) as info:
        main(["demo", "--host", "0.0.0.0", "--no-sign-in", "--port", "0"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --host 0.0.0.0 without sign-in is refused") and "Traceback" not in err


@pytest.fixture()
def certificate(tmp_path: Path) -> tuple[Path, Path]:
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed (apt-get install openssl)")
    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out", str(cert),
         "-days", "1", "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1"],
        check=True, capture_output=True,
    )  # fmt: skip
    return cert, key


def test_tls_serves_https_and_wss_to_the_browser(certificate: tuple[Path, Path]) -> None:
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed")
    executable = CHROMIUM if CHROMIUM.exists() else shutil.which("chromium")
    if executable is None:
        pytest.skip("chromium is not installed (apt-get install chromium)")
    guard = make_guard("127.0.0.1", token=TOKEN, certfile=certificate[0], keyfile=certificate[1])
    server = make_server("127.0.0.1", 0, guard=guard)
    server.gui.add_markdown("Served over TLS")
    try:
        url = url_of(server, guard, with_token=True)
        assert url.startswith("https://127.0.0.1:") and url.endswith(f"/?token={TOKEN}")
        # plain HTTP to the TLS port is not served
        with pytest.raises((http.client.HTTPException, ConnectionError, OSError)):
            get(server.get_port(), "/")
        unverified = ssl.create_default_context()
        unverified.check_hostname = False
        unverified.verify_mode = ssl.CERT_NONE
        # wss without the token is refused (a loaded machine answered a TLS handshake after 10 s once)
        with pytest.raises(InvalidStatus):
            connect(f"wss://127.0.0.1:{server.get_port()}/", subprotocols=[SUBPROTOCOL], ssl=unverified,
                    open_timeout=30)  # fmt: skip
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(executable), args=["--no-sandbox", "--disable-gpu"])
            context = browser.new_context(ignore_https_errors=True)
            page = context.new_page()
            page.goto(url)
            assert page.url == url.split("?")[0]  # the token left the address bar
            page.get_by_text("Served over TLS").wait_for(timeout=60_000)  # came over wss
            cookie = next(c for c in context.cookies() if c["name"] == guard.cookie_name)
            assert cookie["secure"] and cookie["httpOnly"]
            browser.close()
    finally:
        server.stop()


PASSWORD = "correct horse battery staple"


def test_a_password_file_holds_only_a_salted_hash(tmp_path: Path) -> None:
    made = PasswordHash.of(PASSWORD)
    path = tmp_path / "password"
    path.write_text(made.text() + "\n")
    read = PasswordHash.read(path)
    assert read == made and PASSWORD not in path.read_text()
    assert read.verify(PASSWORD) and not read.verify(PASSWORD + "!") and not read.verify("")
    assert PasswordHash.of(PASSWORD).salt != made.salt  # salted: the same password, another hash
    path.write_text("scrypt$16384$8$1$not-base64$x\n")
    with pytest.raises(ValueError, match="not a roadmap3d password file"):
        PasswordHash.read(path)
    with pytest.raises(ValueError, match="cannot read it"):
        PasswordHash.read(tmp_path / "missing")
    with pytest.raises(ValueError, match="at least 12 characters"):
        PasswordHash.of("short")


def test_signing_in_by_password(tmp_path: Path) -> None:
    audit: list = []
    guard = Guard(None, password=PasswordHash.of(PASSWORD), audit=lambda action, **f: audit.append((action, f)))
    server = make_server("127.0.0.1", 0, guard=guard)
    try:
        port = server.get_port()
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
        conn.request("GET", "/")
        page = conn.getresponse()
        assert page.status == 401 and b"type=password" in page.read()  # the page asks for it
        conn.close()
        assert get(port, "/?password=wrong-password-1").status == 401
        assert get(port, f"/?token={PASSWORD.replace(' ', '+')}").status == 401  # a password is not a token
        right = get(port, "/?password=" + PASSWORD.replace(" ", "+"))
        assert right.status == 303 and right.getheader("Location") == "/"
        cookie = right.getheader("Set-Cookie").split(";", 1)[0]
        assert get(port, "/", {"Cookie": cookie}).status == 200
        with websocket(port, Cookie=cookie, Origin=f"http://127.0.0.1:{port}") as ws:
            assert ws.subprotocol == SUBPROTOCOL
    finally:
        server.stop()
    results = [(a, f["result"]) for a, f in audit]
    assert ("sign-in", "refused: wrong password") in results and ("sign-in", "ok") in results
    assert all(PASSWORD not in str(f) for _, f in audit)


def test_the_password_command_and_flag(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    import io

    from app import cli

    path = tmp_path / "app-password"
    monkeypatch.setattr("sys.stdin", io.StringIO(PASSWORD + "\n"))
    with pytest.raises(SystemExit) as info:
        cli.main(["password", str(path)])
    assert info.value.code == 0
    assert path.stat().st_mode & 0o077 == 0 and PASSWORD not in path.read_text()
    assert PasswordHash.read(path).verify(PASSWORD)
    monkeypatch.setattr("sys.stdin", io.StringIO(PASSWORD + "\n"))
    with pytest.raises(SystemExit) as info:
        cli.main(["password", str(path)])
    assert info.value.code == 2 and "exists; give --force" in capsys.readouterr().err
    monkeypatch.setattr("sys.stdin", io.StringIO("short\n"))
    with pytest.raises(SystemExit) as info:
        cli.main(["password", str(tmp_path / "other")])
    assert info.value.code == 2 and not (tmp_path / "other").exists()
    guard = make_guard("0.0.0.0", password_file=path)  # a password signs in: serving beyond loopback is allowed
    assert guard.password is not None and guard.token is None and "token" not in guard.url("0.0.0.0", 8080)
    with pytest.raises(ValueError, match="--password-file and --token contradict"):
        make_guard("127.0.0.1", token=TOKEN, password_file=path)


def test_the_browser_signs_in_by_password(tmp_path: Path) -> None:
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed")
    executable = CHROMIUM if CHROMIUM.exists() else shutil.which("chromium")
    if executable is None:
        pytest.skip("chromium is not installed (apt-get install chromium)")
    path = tmp_path / "password"
    path.write_text(PasswordHash.of(PASSWORD).text())
    guard = make_guard("127.0.0.1", password_file=path)
    server = make_server("127.0.0.1", 0, guard=guard)
    server.gui.add_markdown("Signed in by password")
    try:
        url = url_of(server, guard, with_token=True)
        assert "token" not in url and "password" not in url  # nothing secret to print
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(executable), args=["--no-sandbox", "--disable-gpu"])
            page = browser.new_page()
            page.goto(url)
            page.get_by_label("Password").fill("not the password")
            page.get_by_role("button", name="Sign in").click()
            page.get_by_label("Password").wait_for(timeout=10_000)  # refused: asked again
            page.get_by_label("Password").fill(PASSWORD)
            page.get_by_role("button", name="Sign in").click()
            page.get_by_text("Signed in by password").wait_for(timeout=60_000)  # the app, over its websocket
            assert "password" not in page.url  # the password left the address bar
            browser.close()
    finally:
        server.stop()
