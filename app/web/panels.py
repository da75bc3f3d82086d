"""Optional panels mounted into the app's layout: the place for a new tab.

A panel is a class whose constructor takes a :class:`PanelContext`, builds its widgets inside
a tab it opens itself, and implements :class:`Panel`. To add one:

1. write it in its own module (``app/web/playback.py``, ``app/web/pacs_panel.py``, ...), e.g.::

       class PlaybackPanel(BasePanel):
           def __init__(self, ctx: PanelContext) -> None:
               self.ctx = ctx
               with ctx.layout.view_tab("Play run", viser.Icon.PLAYER_PLAY):   # left, or
                   self.play = ctx.server.gui.add_button("Play")                 # control_tab: right
               self.play.on_click(ctx.guarded(lambda _e: ...))

2. add its class to ``PANELS`` in :mod:`app.web.gui` (the order there is the order of the tabs).

What a panel may use (all on the context): the shared :class:`~app.web.session.Session` (change it
under ``session.lock``, or through its methods, which refuse while a registration runs), the
layout's handles, ``message`` for the status line, ``refresh`` to make the presenter redraw,
``guarded`` to turn a failing callback into a message in the page, and ``server`` for the
scene. It must not block a callback for long: long work goes on its own worker thread,
stopped in :meth:`Panel.close`. The presenter asks each panel whether the patient should be
hidden from the scene (:attr:`Panel.hides_patient`, the calibration view images its phantom
on its own), and tells every panel when the C-arm settings or the data changed
(:meth:`Panel.settings_changed`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import viser

if TYPE_CHECKING:
    from app.web.data import PhantomData
    from app.web.layout import Layout
    from app.web.session import Session


@runtime_checkable
class Panel(Protocol):
    """What the app asks of a mounted panel."""

    @property
    def hides_patient(self) -> bool:
        """True while the panel wants the patient out of the 3D scene."""
        ...

    def settings_changed(self) -> None:
        """The C-arm settings or the data changed (called on a callback thread)."""
        ...

    def close(self) -> None:
        """Stop the panel's threads (the app is closing)."""
        ...


class BasePanel:
    """Defaults for :class:`Panel`: shows the patient, ignores changes, nothing to stop."""

    @property
    def hides_patient(self) -> bool:
        return False

    def settings_changed(self) -> None:
        return None

    def close(self) -> None:
        return None


def _ignore(_pose: Any) -> None:
    return None


@dataclass(frozen=True)
class PanelContext:
    """What the app hands a panel's constructor."""

    server: viser.ViserServer
    session: Session
    layout: Layout
    #: The built-in phantom (the session's data may be the user's instead).
    phantom: PhantomData
    #: Show a line in the status area (``error=True``: red, and a notification in every tab).
    message: Callable[..., None]
    #: Make the presenter redraw the scene and the pictures now.
    refresh: Callable[[], None]
    #: Wrap a callback: a ValueError becomes a message, anything else a logged error message.
    guarded: Callable[[Callable[..., None]], Callable[..., None]]
    #: The limit of one browser upload (bytes); every transfer is also held to the app's budget.
    max_upload_bytes: int = 512_000_000
    #: Let the 3-D scene follow a played run (an :class:`app.web.presenter.FollowedPose`; None: back
    #: to the session). The presenter draws it at its next frame.
    follow: Callable[[Any], None] = _ignore


PanelFactory = Callable[[PanelContext], Panel]


def mount(factories: tuple[PanelFactory, ...], ctx: PanelContext) -> list[Panel]:
    """Build the panels; each must implement :class:`Panel`."""
    panels: list[Panel] = []
    for factory in factories:
        panel = factory(ctx)
        if not isinstance(panel, Panel):
            raise TypeError(f"{factory!r} built {type(panel).__name__}, which does not implement app.panels.Panel")
        panels.append(panel)
    return panels


__all__ = ["BasePanel", "Panel", "PanelContext", "PanelFactory", "mount"]
