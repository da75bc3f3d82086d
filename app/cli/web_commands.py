"""``demo`` and ``app``: start the web app (:func:`app.web.main.run_app`) with the command's options."""

from __future__ import annotations

import os
from dataclasses import fields

from app.cli.configs import App, Demo, Serving
from app.cli.errors import UserError
from app.web.main import run_app as serve


def _serving(options: Serving) -> dict:
    """How the app is served (address, sign-in, TLS, origins, logging), as :func:`serve` takes it."""
    return {f.name: getattr(options, f.name) for f in fields(Serving)}


def run_demo(options: Demo) -> int:
    """The web app on the built-in phantom."""
    return serve(volume=None, image=None, **_serving(options))


def run_app(options: App) -> int:
    """The web app on the user's data (or the phantom), with its PACS tab and DICOM node if asked."""
    if options.listen_port is not None:
        from registration.io.node import ENV_APP_NODE_ALLOW, ENV_APP_NODE_PORT, check_ae_title

        if not options.allow:
            raise UserError("--listen-port needs --allow AE (the C-arm's AE title)")
        titles = [check_ae_title(a, "--allow") for a in options.allow]
        os.environ[ENV_APP_NODE_PORT] = str(options.listen_port)
        os.environ[ENV_APP_NODE_ALLOW] = "\\".join(titles)
    elif options.allow:
        raise UserError("--allow needs --listen-port")
    if options.pacs is not None:
        from registration.io.pacs import ENV_URL, PacsSettings

        PacsSettings.resolve(options.pacs)  # a bad URL or config is an error now, not in the page
        os.environ[ENV_URL] = options.pacs  # the PACS tab (app/web/pacs_panel.py) reads it
    return serve(
        volume=options.volume, image=options.image, frame=options.frame, allow_share=options.allow_share,
        max_upload_mb=options.max_upload_mb, sid_mm=options.sid_mm, sod_mm=options.sod_mm,
        isocenter=options.isocenter, **_serving(options),
    )  # fmt: skip
