"""The PACS client's answers to a server that fails (registration/io/pacs.py).

A small HTTP server on 127.0.0.1 plays the PACS: it answers each request from a script (a
status code, or dropping the connection). Busy answers and dropped connections are tried
again with back-off until the script lets one through; 401/403/404/5xx become messages that
name the server and the request and never the password.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from registration.io import pacs as pacs_module
from registration.io.pacs import Pacs, PacsError, PacsSettings

STUDY = {"0020000D": {"vr": "UI", "Value": ["1.2.3.4"]}, "00100020": {"vr": "LO", "Value": ["P1"]}}
PASSWORD = "pw-never-shown"


def later_page(path: str) -> bool:
    """A request for the results after the first page (``offset=N``, N > 0)."""
    from urllib.parse import parse_qs, urlsplit

    return int(parse_qs(urlsplit(path).query).get("offset", ["0"])[0]) > 0


class Script:
    """What the server answers, request by request (the last entry repeats)."""

    def __init__(self) -> None:
        self.answers: list[int | str] = [200]
        self.requests: list[str] = []

    def next(self) -> int | str:
        return self.answers.pop(0) if len(self.answers) > 1 else self.answers[0]


@pytest.fixture()
def server(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[str, Script]]:
    monkeypatch.setattr(pacs_module, "RETRY_WAIT_MS", 50)  # short back-off: the test waits 50 + 100 ms
    script = Script()

    class Handler(BaseHTTPRequestHandler):
        def log_message(self, *args: object) -> None:
            pass

        def do_GET(self) -> None:  # noqa: N802
            if not later_page(self.path):
                script.requests.append(self.path)
            answer = script.next()
            if answer == "drop":
                self.connection.close()  # no answer at all: a connection error for the client
                return
            # one study, then an empty page (the client asks for the rest with an offset)
            found = [] if later_page(self.path) else [STUDY]
            body = json.dumps(found).encode() if answer == 200 else b"{}"
            self.send_response(int(answer))
            self.send_header("Content-Type", "application/dicom+json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}/dicom-web", script
    httpd.shutdown()
    httpd.server_close()


def client(url: str, attempts: int = 3) -> Pacs:
    return Pacs(PacsSettings(url, username="alice", password=PASSWORD, timeout_s=(2.0, 2.0), attempts=attempts))


def test_busy_answers_and_dropped_connections_are_tried_again(server: tuple[str, Script]) -> None:
    url, script = server
    script.answers = [503, 200]
    assert [s.study_uid for s in client(url).studies()] == ["1.2.3.4"]
    assert len(script.requests) == 2
    script.requests.clear()
    script.answers = ["drop", "drop", 200]
    assert [s.study_uid for s in client(url).studies()] == ["1.2.3.4"]
    assert len(script.requests) == 3
    script.requests.clear()
    script.answers = ["drop"]
    with pytest.raises(PacsError, match="cannot connect after 3 attempts") as info:
        client(url).studies()
    assert url in str(info.value) and "searching studies" in str(info.value)
    assert len(script.requests) == 3


@pytest.mark.parametrize(
    ("code", "meaning"),
    [
        (401, "wrong or missing credentials"),
        (403, "the account may not do this"),
        (404, "not found on the server"),
        (500, "the server failed"),
    ],
)
def test_errors_name_the_server_and_the_request(server: tuple[str, Script], code: int, meaning: str) -> None:
    url, script = server
    script.answers = [code]
    with pytest.raises(PacsError) as info:
        client(url).series("1.2.3.4")
    text = str(info.value)
    assert f"PACS {url}" in text and f"HTTP {code} ({meaning}" in text
    assert "GET /dicom-web/studies/1.2.3.4/series" in text  # the request, without its query
    assert PASSWORD not in text and "alice" not in text
    assert len(script.requests) == 1  # not a busy answer: asked once


def test_a_server_that_stays_busy_is_given_up(server: tuple[str, Script]) -> None:
    url, script = server
    script.answers = [503]
    with pytest.raises(PacsError, match=r"HTTP 503 \(the server failed"):
        client(url, attempts=3).studies()
    assert len(script.requests) == 3
