"""``instrument serve``: the live web view of the run store and the OPC UA server for the robot cell.

Public names: ``create_app`` and ``WebSettings`` (the FastAPI app, one router per resource), ``StoreReader``
(read access to the store), ``write_live_frames`` (re-exported from ``procedures.engine``: what the engine
calls after each pose so the live page shows the frames), ``InstrumentOpcUa`` and ``OpcUaSettings``,
``RunLauncher`` (runs as child processes), ``serve`` and ``ServeOptions`` (both servers in one event
loop). Pages, API and security: docs/web_view.md; the OPC UA address space: docs/opcua.md.
"""

from procedures.engine import write_live_frames
from procedures.serve._app import WebSettings, create_app
from procedures.serve._frames import latest_frames, stripe_lines
from procedures.serve._launcher import LaunchRefused, RunLauncher, parse_overrides
from procedures.serve._opcua import NAMESPACE, InstrumentOpcUa, OpcUaSettings
from procedures.serve._reader import StoreReader, robot_of
from procedures.serve._security import TOKEN_ENV, is_loopback, new_token
from procedures.serve._server import ServeOptions, serve

__all__ = [
    "NAMESPACE", "TOKEN_ENV", "InstrumentOpcUa", "LaunchRefused", "OpcUaSettings", "RunLauncher", "ServeOptions",
    "StoreReader", "WebSettings", "create_app", "is_loopback", "latest_frames", "new_token", "parse_overrides",
    "robot_of", "serve", "stripe_lines", "write_live_frames",
]
