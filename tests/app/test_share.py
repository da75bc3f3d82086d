"""The share tunnel (a public URL to the app) is refused unless --allow-share."""

from __future__ import annotations

import time

import msgspec
import pytest
import viser
import viser._viser
from websockets.sync.client import connect

from app.web.main import make_server


class FakeTunnel:
    """Stands in for viser's tunnel to share.viser.studio (no network in tests)."""

    created: list[int] = []

    def __init__(self, share_domain: str, local_port: int) -> None:
        FakeTunnel.created.append(local_port)

    def get_status(self) -> str:
        return "failed"

    def get_url(self) -> None:
        return None

    def close(self) -> None:
        pass

    def on_connect(self, fn):  # pragma: no cover - never connects
        return fn

    def on_disconnect(self, fn):  # pragma: no cover
        return fn


def send_share_request(server: viser.ViserServer) -> None:
    """What viser's share button sends, written by hand over the websocket."""
    url = f"ws://127.0.0.1:{server.get_port()}"
    with connect(url, subprotocols=[f"viser-v{viser.__version__}"]) as ws:
        ws.send(msgspec.msgpack.encode({"type": "ShareUrlRequest"}))
        time.sleep(0.5)


@pytest.mark.parametrize("allow", [False, True])
def test_share_requests_need_allow_share(monkeypatch: pytest.MonkeyPatch, allow: bool) -> None:
    monkeypatch.setattr(viser._viser, "ViserTunnel", FakeTunnel)
    FakeTunnel.created.clear()
    server = make_server("127.0.0.1", 0, allow_share=allow)
    try:
        send_share_request(server)
        deadline = time.monotonic() + 2.0
        while allow and not FakeTunnel.created and time.monotonic() < deadline:
            time.sleep(0.05)
        assert bool(FakeTunnel.created) is allow
        # Python-side requests are refused too.
        if not allow:
            assert server.request_share_url() is None
            assert not FakeTunnel.created
    finally:
        server.stop()


def test_binds_localhost_by_default() -> None:
    server = make_server(port=0)
    try:
        assert server.get_host() == "127.0.0.1"
    finally:
        server.stop()
