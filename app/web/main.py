"""``roadmap3d demo`` / ``roadmap3d app``: start the web app and serve until Ctrl-C."""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
import webbrowser
from pathlib import Path
from types import FrameType

import viser

from app.web.data import AppConfig, FileData, PhantomData
from app.web.gui import RoadmapApp
from app.web.session import Session
from app.web.share import refuse_share_requests
from app.web.signin import (
    ENV_TOKEN,
    Guard,
    PasswordHash,
    check_token,
    guarded,
    new_token,
    parse_origins,
    tls_context,
)
from app.web.upload import shutdown_readers
from registration.io import audit

log = logging.getLogger(__name__)

#: The panel's accent colour (a calm clinical blue).
BRAND_RGB = (34, 139, 230)


def make_server(
    host: str = "127.0.0.1", port: int = 8080, *, allow_share: bool = False, guard: Guard | None = None
) -> viser.ViserServer:
    """A viser server in the app's dark theme; share-tunnel requests refused unless allowed.
    ``guard``: sign-in, origin check and TLS (:mod:`app.web.signin`); None serves without them."""
    server = guarded(guard, lambda: viser.ViserServer(host=host, port=port, label="3D roadmap", verbose=False))
    if not allow_share:
        refuse_share_requests(server)
    server.gui.configure_theme(dark_mode=True, show_logo=False, show_share_button=allow_share, brand_color=BRAND_RGB)
    # Oblique from the patient's left, level with the head: the beam, and the image on the detector.
    server.initial_camera.position = (0.86, 0.22, 0.68)
    server.initial_camera.look_at = (0.0, 0.1, 0.0)
    server.initial_camera.up = (0.0, -1.0, 0.0)
    return server


#: Hosts that only this machine can reach.
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")
#: After Ctrl-C/SIGTERM the process ends within this many seconds, whatever a thread is doing.
EXIT_GRACE_S = 5.0


def url_of(server: viser.ViserServer, guard: Guard | None = None, *, with_token: bool = False) -> str:
    """The address the server really listens on (a wildcard host as given: every interface);
    https with TLS, and ``/?token=TOKEN`` when ``with_token`` and the guard signs in."""
    host = server.get_host()
    shown = f"[{host}]" if ":" in host else host
    if guard is None:
        return f"http://{shown}:{server.get_port()}"
    url = guard.url(host, server.get_port())
    return url if with_token else url.split("?", 1)[0].rstrip("/")


def make_guard(
    host: str,
    *,
    token: str | None = None,
    no_sign_in: bool = False,
    certfile: Path | None = None,
    keyfile: Path | None = None,
    allow_origin: tuple[str, ...] = (),
    password_file: Path | None = None,
) -> Guard:
    """The app's guard from its flags: the password file's hash, else the token given, else
    ROADMAP3D_TOKEN, else a new random one; serving beyond this machine without sign-in is refused."""
    password = None
    if password_file is not None:
        if token is not None or no_sign_in:
            raise ValueError("--password-file and " + ("--token" if token is not None else "--no-sign-in")
                             + " contradict each other")  # fmt: skip
        password = PasswordHash.read(password_file)
    if no_sign_in:
        if token is not None:
            raise ValueError("--token and --no-sign-in contradict each other")
        if host not in LOOPBACK_HOSTS:
            raise ValueError(
                f"--host {host} without sign-in is refused: anyone on the network could see the patient's images. "
                "Drop --no-sign-in (a token is printed), or serve on 127.0.0.1"
            )
        chosen = None
    elif password is not None:
        chosen = None
    else:
        chosen = check_token(token or os.environ.get(ENV_TOKEN) or new_token())
    if keyfile is not None and certfile is None:
        raise ValueError("--keyfile needs --certfile")
    context = tls_context(certfile, keyfile) if certfile is not None else None
    return Guard(chosen, context, parse_origins(allow_origin), audit=audit.record, password=password)


def network_warning(host: str, port: int) -> str | None:
    """The warning printed when the app listens beyond this machine (None on a loopback host)."""
    if host in LOOPBACK_HOSTS:
        return None
    where = "every network interface" if host in ("0.0.0.0", "::", "") else f"{host}"
    reachable = ""
    if host in ("0.0.0.0", "::", ""):
        try:
            import socket

            address = socket.gethostbyname(socket.gethostname())
            reachable = f" (for example http://{address}:{port})"
        except OSError:
            reachable = ""
    return (
        f"roadmap3d: WARNING: listening on {where}{reachable}. Whoever has the address with its token can see "
        "the patient's images and drive the one shared session; without --certfile/--keyfile the token and the "
        "images cross the network unencrypted (see docs/deployment.md)."
    )


def _exit_soon(code: int, grace_s: float = EXIT_GRACE_S) -> None:
    """End the process ``grace_s`` seconds from now if it is still alive (a hung thread must not
    keep a stopped server running)."""

    def watchdog() -> None:
        time.sleep(grace_s)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)

    threading.Thread(target=watchdog, name="exit-watchdog", daemon=True).start()


def build_app(
    server: viser.ViserServer,
    config: AppConfig | None = None,
    *,
    data: FileData | None = None,
    max_upload_mb: float = 512.0,
    announce: bool = False,
) -> RoadmapApp:
    """Prepare the data (showing progress in the page) and build the app on ``server``.

    ``data``: the user's volume and image; None starts on the built-in phantom.
    """
    config = config or AppConfig.from_env()
    gui = server.gui
    note = gui.add_markdown("**Preparing the 3D roadmap…**")
    bar = gui.add_progress_bar(0.0, animated=True)
    start = time.perf_counter()
    printed = {"what": "", "at": -1e9}

    def progress(message: str, fraction: float) -> None:
        note.content = f"**Preparing the 3D roadmap…**  \n{message}"
        bar.value = max(bar.value, min(100.0, fraction * 100.0))
        now = time.perf_counter()
        what = message.split(":", 1)[0]  # a new step, or the same step's elapsed time every 10 s
        if announce and (what != printed["what"] or now - printed["at"] >= 10.0):
            print(f"  [{now - start:5.1f} s] {message}", file=sys.stderr, flush=True)
            printed.update(what=what, at=now)

    phantom = PhantomData(config, progress)
    session = Session(data if data is not None else phantom, config)
    fmt = session.settings.volume_format_cm
    source = session.data
    source.volume(fmt)
    # Two cores: the renderer's pyramid and the surfaces + first image are prepared side by side.
    renderer = threading.Thread(target=source.renderer, args=(fmt,), name="prepare-renderer")
    renderer.start()
    source.meshes(fmt)
    progress("Forming the first X-ray image", 0.7)
    session.xray()
    renderer.join()
    progress("Ready", 1.0)
    note.remove()
    bar.remove()
    app = RoadmapApp(server, session, phantom=phantom, max_upload_mb=max_upload_mb)
    # Later preparations (another volume format) report in the status line.
    phantom.progress = lambda message, _fraction: app.controller.preparing(message)
    # Said before the presenter starts: its first frame must not overwrite it (it restores what it found).
    if data is None:
        app.message("Ready. Press **T4**, then **Register**.")
    else:
        app.message(
            f"Your data is loaded (iso-center {data.isocenter_text}). Press **Register** to correct the roadmap."
        )
    app.start()
    return app


def _check_data_options(
    volume: Path | None,
    image: Path | None,
    max_upload_mb: float,
    sid_mm: float | None,
    sod_mm: float | None,
    isocenter: str | None,
) -> None:
    if (volume is None) != (image is None):
        raise ValueError("--volume and --image go together (or neither, for the built-in phantom)")
    if max_upload_mb <= 0:
        raise ValueError(f"--max-upload-mb must be positive, got {max_upload_mb}")
    if image is None and (sid_mm is not None or sod_mm is not None):
        raise ValueError("--sid-mm/--sod-mm apply to --volume/--image only")
    if image is None and isocenter is not None:
        raise ValueError("--isocenter applies to --volume/--image only")


def _announce(server: viser.ViserServer, guard: Guard, password_file: Path | None, open_browser: bool) -> None:
    """Print the signed address (the only place the token is shown), warn when the app is
    reachable from the network, and open the browser if asked."""
    signed = url_of(server, guard, with_token=True)
    by_password = f"; sign in with the password of {password_file}" if guard.password is not None else ""
    print(f"roadmap3d: serving on {signed}  (Ctrl-C to stop{by_password})", flush=True)
    warning = network_warning(server.get_host(), server.get_port())
    if warning:
        print(warning, file=sys.stderr, flush=True)
    if open_browser:
        threading.Thread(target=webbrowser.open, args=(signed,), daemon=True).start()


def _stop_on_signals() -> None:
    """SIGTERM and SIGINT end the serving loop (as Ctrl-C), from the main thread."""

    def terminate(_signum: int, _frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, terminate)
        signal.signal(signal.SIGINT, signal.default_int_handler)  # even if started with SIGINT ignored


def run_app(
    host: str,
    port: int,
    volume: Path | None,
    image: Path | None,
    frame: int | None = None,
    allow_share: bool = False,
    max_upload_mb: float = 512.0,
    open_browser: bool = False,
    sid_mm: float | None = None,
    sod_mm: float | None = None,
    isocenter: str | None = None,
    token: str | None = None,
    no_sign_in: bool = False,
    certfile: Path | None = None,
    keyfile: Path | None = None,
    allow_origin: tuple[str, ...] = (),
    password_file: Path | None = None,
    verbose: bool = False,
) -> int:
    """Serve the app until Ctrl-C (or SIGTERM); returns the exit code. Sign-in, origins and TLS
    as :func:`make_guard`. ``sid_mm`` / ``sod_mm``
    supply the distances of an ``image`` that lacks them; ``isocenter`` places it (as
    ``register --isocenter``: "x,y,z" mm or "volume-center"; default the volume's
    IsocenterPosition, else the world origin); ``verbose``: log each registration's plan."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if verbose:
        logging.getLogger("app.web.session").setLevel(logging.INFO)
    config = AppConfig.from_env()
    start = time.perf_counter()
    _check_data_options(volume, image, max_upload_mb, sid_mm, sod_mm, isocenter)
    guard = make_guard(host, token=token, no_sign_in=no_sign_in, certfile=certfile, keyfile=keyfile,
                       allow_origin=allow_origin, password_file=password_file)  # fmt: skip
    data = None
    if volume is not None and image is not None:
        # Read (and reject with a message naming the file and tag) before serving anything.
        data = FileData.from_paths(
            volume, image, frame=frame, config=config, sid_mm=sid_mm, sod_mm=sod_mm, isocenter=isocenter
        )
        print(f"roadmap3d: iso-center {data.isocenter_text}", flush=True)
    server = make_server(host, port, allow_share=allow_share, guard=guard)
    url = url_of(server, guard)
    _announce(server, guard, password_file, open_browser)
    _stop_on_signals()
    app: RoadmapApp | None = None
    try:
        app = build_app(server, config, data=data, max_upload_mb=max_upload_mb, announce=True)
        print(f"roadmap3d: ready after {time.perf_counter() - start:.1f} s at {url}", flush=True)
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        print("\nroadmap3d: stopping", file=sys.stderr, flush=True)
    finally:
        _exit_soon(0)  # whatever hangs below or in another thread, the process ends in EXIT_GRACE_S
        shutdown_readers()  # upload readers ended, their temporary folders removed
        if app is not None:
            app.close()
        server.stop()
    return 0
