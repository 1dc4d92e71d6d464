"""``visnerf serve`` and ``visnerf submit``, registered into the ``visnerf`` command line."""

import argparse
import logging
import signal
import sys
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from visnerf_server.registry import SCENE_ID_PATTERN, is_valid_scene_id
from visnerf_server.settings_options import add_settings_options, given_settings, option_name

LOOPBACK_HOSTS = {"127.0.0.1", "::1", "localhost"}


def register(subparsers: Any) -> None:
    serve = subparsers.add_parser(
        "serve", help="serve trained scenes over HTTP and WebSocket", description="Run the render server."
    )
    serve.add_argument("--host", default="127.0.0.1", help="interface to listen on (default: loopback only)")
    serve.add_argument("--port", type=int, default=8000)
    serve.add_argument(
        "--checkpoints",
        type=Path,
        default=None,
        metavar="DIR",
        help="folder of <id>.safetensors (default: the bundled checkpoints/)",
    )
    serve.add_argument("--no-client", action="store_true", help="serve the API only, not the web client")
    serve.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    add_settings_options(serve)
    serve.set_defaults(func=serve_command)

    submit = subparsers.add_parser(
        "submit",
        help="upload a finished checkpoint to a running server",
        description="Upload CKPT to the server at URL (e.g. http://host:8000). The token comes from --token, "
        "VISNERF_TOKEN, VISNERF_TOKEN_FILE or the server's generated token file on this machine.",
    )
    submit.add_argument("checkpoint", type=Path, metavar="CKPT")
    submit.add_argument("url", metavar="URL")
    submit.add_argument("--id", default=None, help="scene id (default: the file stem)")
    submit.add_argument("--token", default=None, help="upload token (default: $VISNERF_TOKEN)")
    submit.add_argument("--timeout", type=float, default=300.0, help="seconds to wait for the server")
    submit.set_defaults(func=submit_command)


class _JsonFormatter(logging.Formatter):
    """Access-log lines are already JSON; other records become JSON objects too."""

    def format(self, record: logging.LogRecord) -> str:
        if record.name == "visnerf_server.access":
            return record.getMessage()
        import json

        entry = {"level": record.levelname.lower(), "logger": record.name, "message": record.getMessage()}
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry)


def configure_logging(level: str, log_format: str) -> None:
    handler = logging.StreamHandler(sys.stderr)
    if log_format == "json":
        handler.setFormatter(_JsonFormatter())
    else:
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level.upper())


def serve_command(args: argparse.Namespace) -> int:
    from visnerf_server.app import create_app
    from visnerf_server.serving import serve
    from visnerf_server.settings import Settings

    overrides: dict[str, Any] = given_settings(args)
    if args.checkpoints is not None:
        overrides["checkpoints_dir"] = args.checkpoints.resolve()
    if args.no_client:
        overrides["client_dir"] = None
    try:
        settings = Settings(**overrides)
    except ValidationError as exc:  # a value out of its range: name the option and the rule
        problems = "; ".join(f"{option_name(str(e['loc'][0]))}: {e['msg']}" if e["loc"] else
                             e["msg"].removeprefix("Value error, ") for e in exc.errors())
        print(f"visnerf serve: error: {problems}", file=sys.stderr)
        return 2
    configure_logging(args.log_level, settings.log_format)
    log = logging.getLogger("visnerf_server")
    if args.host not in LOOPBACK_HOSTS:
        log.warning("listening on %s: the server is reachable from other machines", args.host)
    log.info("checkpoints: %s", settings.checkpoints_dir)
    app = create_app(settings)
    # uvicorn shuts down gracefully on SIGTERM, then re-raises the signal; a no-op handler here makes
    # that re-raise harmless so a clean shutdown exits with status 0.
    signal.signal(signal.SIGTERM, lambda signum, frame: None)
    started = serve(  # uvicorn.run, and the stop signal also stops the renders in flight (``serving``)
        app,
        host=args.host,
        port=args.port,
        log_config=None,
        log_level=args.log_level,
        access_log=False,
        timeout_graceful_shutdown=5,
        ws_max_size=settings.ws_max_message_bytes,  # the protocol refuses bigger frames (close 1009)
        proxy_headers=False,  # the app believes X-Forwarded-For from ``trusted_proxies`` only
    )
    return 0 if started else 3


def submit_command(args: argparse.Namespace) -> int:
    from visnerf.upload import UploadError, upload_checkpoint

    path: Path = args.checkpoint
    if not path.is_file():
        print(f"error: {path} is not a file", file=sys.stderr)
        return 2
    scene_id = args.id if args.id is not None else path.name.removesuffix(".safetensors")
    if not is_valid_scene_id(scene_id):
        print(f"error: scene id {scene_id!r} must match {SCENE_ID_PATTERN} (use --id)", file=sys.stderr)
        return 2
    try:
        done = upload_checkpoint(path, args.url, scene_id, args.token, args.timeout)
    except UploadError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2 if str(exc).startswith("no token") else 1
    print(f"{'created' if done.created else 'replaced'} scene {scene_id!r} ({done.size} bytes) at {done.url}")
    return 0
