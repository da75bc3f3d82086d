"""Refuse viser's share tunnel unless the user asked for it.

viser's panel can ask the server (a ``ShareUrlRequest`` websocket message) to open a public
tunnel to share.viser.studio that exposes the app, and with it possibly patient data, to the
internet. Hiding the button (``configure_theme(show_share_button=False)``) does not stop a
hand-made request, so the server-side handler is replaced here: the request is answered with
a notification to the asking tab and nothing is opened.
"""

from __future__ import annotations

import logging
from typing import Any

import viser
from viser import _messages  # the message types are not re-exported; pinned by the tests

log = logging.getLogger(__name__)

REFUSAL = "Sharing is disabled: this app may show patient data. Start it with --allow-share to enable."


def refuse_share_requests(server: viser.ViserServer) -> None:
    """Make ``server`` ignore share-tunnel requests from browsers (and from Python)."""
    websock = server._websock_server  # noqa: SLF001 - the only place viser routes the message
    for message_cls in (_messages.ShareUrlRequest, _messages.ShareUrlDisconnect):
        if message_cls in websock._incoming_handlers:  # noqa: SLF001
            websock.unregister_handler(message_cls)

    def refuse(client_id: Any, _message: Any) -> None:
        log.warning("refused a share-tunnel request from client %s", client_id)
        client = server.get_clients().get(client_id)
        if client is not None:
            try:
                client.add_notification("Sharing disabled", REFUSAL, color="red", auto_close_seconds=8.0)
            except Exception:  # the tab may be gone already
                pass

    websock.register_handler(_messages.ShareUrlRequest, refuse)

    def request_share_url(verbose: bool = True) -> str | None:
        log.warning("refused a share-tunnel request (start with --allow-share to enable)")
        return None

    # Belt and braces: any other path into the tunnel goes through this method.
    server.request_share_url = request_share_url  # type: ignore[method-assign]
