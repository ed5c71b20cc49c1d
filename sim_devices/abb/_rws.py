"""Robot Web Services 1.0 (RobotWare 6) over HTTP/1.1, as an IRC5 serves it to ``abb_robot_client``.

Authentication is HTTP Digest (MD5, ``qop="auth"``, realm ``validusers@robapi.abb``): a request
without a session cookie or valid credentials gets 401 and a challenge; a valid answer opens a
session (cookies ``-http-session-`` and ``ABBCX``; at most ``max_sessions``, then 503). Every
``?json=1`` answer is HAL-style JSON with ``Content-Type: application/json`` (the client compares
that header exactly): ``{"_links": {...}, "_embedded": {"_state": [{"_type": ..., "_title": ...,
field: "text", ...}]}}``; an error carries ``_embedded.status.code``/``msg``. Actions answer 204,
a file upload 201, a new subscription 201 with an XHTML body whose ``<a href="ws://…/poll/N"
rel="self">`` the client opens as a WebSocket (``_websocket``) carrying XHTML events, one ``<li>``
per change, in the classes the client's expressions look for (``pnl-ctrlstate-ev``,
``rap-ctrlexecstate-ev``, ``ios-signalstate-ev``, ``rap-data``, ``elog-message-ev``,
``pnl-opmode-ev``).

Faults (the twin's ``FaultPlan``, optional ``path`` parameter: only requests whose path contains
it): ``exception`` answers with ``status`` (default 503, "too many active connections"),
``drop_reply`` reads the request and never answers (the connection stays open for ``seconds``,
default until the twin stops), ``delay``/``slow`` answer ``seconds`` late, ``disconnect`` closes
the connection without an answer.
"""

from __future__ import annotations

import hashlib
import html
import itertools
import json
import secrets
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import parse_qs, unquote, urlsplit

from sim_devices.abb._controller import IRC5, RWS_BAD_VALUE, RWS_NOT_FOUND, RwsError
from sim_devices.abb._websocket import SUBPROTOCOL, WebSocketConnection, accept_key
from sim_devices.faults import FaultKind, FaultPlan

REALM = "validusers@robapi.abb"
HTTP_FAULTS = (FaultKind.EXCEPTION, FaultKind.DROP_REPLY, FaultKind.DELAY, FaultKind.DISCONNECT)


def _md5(text: str) -> str:
    return hashlib.md5(text.encode()).hexdigest()


def _parse_digest(header: str) -> dict[str, str]:
    fields: dict[str, str] = {}
    for part in _split_commas(header[len("Digest "):]):
        key, _, value = part.strip().partition("=")
        fields[key.strip().lower()] = value.strip().strip('"')
    return fields


def _split_commas(text: str) -> list[str]:
    parts, current, quoted = [], "", False
    for char in text:
        if char == '"':
            quoted = not quoted
        if char == "," and not quoted:
            parts.append(current)
            current = ""
        else:
            current += char
    return [*parts, current] if current else parts


class Subscription:
    """One subscription group: the resources it carries (controller keys → subscribed paths)."""

    def __init__(self, number: int, resources: dict[str, str]) -> None:
        self.number = number
        self.resources = resources
        self.sockets: list[WebSocketConnection] = []


class RwsServer:
    """The HTTP side of the twin (see the module docstring).

    Parameters
    ----------
    controller : IRC5
        Answers every resource.
    host, port : str, int
        Where to listen (port 0: any).
    faults : FaultPlan
        Transport faults are taken from it.
    """

    def __init__(self, controller: IRC5, host: str, port: int, faults: FaultPlan) -> None:
        self.controller = controller
        self.config = controller.config
        self.faults = faults
        self.nonces: set[str] = set()
        self.sessions: dict[str, str] = {}  # ABBCX → -http-session-
        self.subscriptions: dict[int, Subscription] = {}
        self._numbers = itertools.count(1)
        self._lock = threading.Lock()
        self.requests = 0
        self.stopping = threading.Event()
        self._connections: set[socket.socket] = set()
        outer = self

        class Handler(_Handler):
            server_ref = outer

        class Server(ThreadingHTTPServer):
            daemon_threads = True
            allow_reuse_address = True

        self.httpd = Server((host, port), Handler)
        self.port = int(self.httpd.server_address[1])
        self.host = host
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.1},
                                        name="abb-rws", daemon=True)
        controller.listeners.append(self._event)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self.stopping.set()
        self.httpd.shutdown()
        self.httpd.server_close()
        self.drop_connections()
        self._thread.join(2.0)

    def drop_connections(self) -> None:
        with self._lock:
            connections = list(self._connections)
            groups = list(self.subscriptions.values())
        for group in groups:
            for ws in group.sockets:
                ws.close()
        for conn in connections:
            try:
                conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    # ----------------------------------------------------------------------------- subscriptions
    def subscribe(self, form: dict[str, list[str]]) -> Subscription:
        resources: dict[str, str] = {}
        for number in form.get("resources", []):
            path = form.get(number, [""])[0]
            key = self._resource_key(path)
            if key is None:
                raise RwsError(400, RWS_BAD_VALUE, f"resource {path!r} cannot be subscribed")
            resources[key] = path
        with self._lock:
            group = Subscription(next(self._numbers), resources)
            self.subscriptions[group.number] = group
        return group

    def _resource_key(self, path: str) -> str | None:
        if path in ("/rw/panel/ctrlstate", "/rw/panel/opmode", "/rw/rapid/execution;ctrlexecstate", "/rw/elog/0"):
            return path
        if path.startswith("/rw/iosystem/signals/") and path.endswith(";state"):
            name = path[:-len(";state")].rsplit("/", 1)[-1]
            self.controller.signal(name)
            return f"signal:{name}"
        if path.startswith("/rw/rapid/symbol/data/RAPID/") and path.endswith(";value"):
            symbol = path[len("/rw/rapid/symbol/data/RAPID/"):-len(";value")]
            return f"symbol:{self.controller._symbol_key(symbol)}"
        return None

    def _event(self, key: str, value: str) -> None:
        with self._lock:
            groups = [g for g in self.subscriptions.values() if key in g.resources and g.sockets]
        for group in groups:
            text = event_xhtml(self.host, self.port, group, key, group.resources[key], value)
            for ws in list(group.sockets):
                ws.send_text(text)

    # ----------------------------------------------------------------------------- faults
    def take_fault(self, path: str) -> Any:
        for kind in (*HTTP_FAULTS, FaultKind.SLOW):
            armed = self.faults.peek(kind)
            if armed is not None and str(armed.params.get("path", "")) in path:
                if kind is FaultKind.SLOW:
                    return armed  # until cleared: never consumed
                return self.faults.take(kind)
        return None


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    server_ref: RwsServer
    server_version = "Robot Web Services"
    sys_version = ""

    def log_message(self, format: str, *args: Any) -> None:  # the twin is quiet
        pass

    def setup(self) -> None:
        super().setup()
        self.connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # no Nagle wait on small answers
        with self.server_ref._lock:
            self.server_ref._connections.add(self.connection)

    def finish(self) -> None:
        with self.server_ref._lock:
            self.server_ref._connections.discard(self.connection)
        try:
            super().finish()
        except OSError:
            pass

    # ----------------------------------------------------------------------------- plumbing
    def do_GET(self) -> None:
        self._handle("GET")

    def do_POST(self) -> None:
        self._handle("POST")

    def do_PUT(self) -> None:
        self._handle("PUT")

    def do_DELETE(self) -> None:
        self._handle("DELETE")

    def _handle(self, method: str) -> None:
        rws = self.server_ref
        length = int(self.headers.get("Content-Length") or 0)
        body = self.rfile.read(length) if length else b""
        with rws._lock:
            rws.requests += 1
        split = urlsplit(self.path)
        path = unquote(split.path)
        query = parse_qs(split.query, keep_blank_values=True)
        fault = rws.take_fault(path)
        if fault is not None and self._apply_fault(fault):
            return
        session = self._authenticate(method)
        if session is None:
            return
        try:
            if path.startswith("/poll/") and method == "GET":
                self._websocket(int(path.rsplit("/", 1)[-1]))
                return
            status, payload, content_type = self._route(method, path, query, body)
        except RwsError as error:
            self._send_json(error.status, {"_links": {"base": {"href": self._base()}},
                                           "_embedded": {"status": {"code": error.code, "msg": error.message}}})
            return
        except (ValueError, KeyError, IndexError) as exc:
            self._send_json(400, {"_embedded": {"status": {"code": RWS_BAD_VALUE, "msg": f"bad request: {exc}"}}})
            return
        self._send(status, payload, content_type)

    def _apply_fault(self, fault: Any) -> bool:
        """Act on a transport fault; True when the request gets no normal answer."""
        kind, seconds = fault.kind, float(fault.params.get("seconds", 0.0))
        if kind is FaultKind.EXCEPTION:
            status = int(fault.params.get("status", 503))
            message = "too many active connections" if status == 503 else "injected error"
            self._send_json(status, {"_embedded": {"status": {"code": -1073445859, "msg": message}}})
            return True
        if kind is FaultKind.DROP_REPLY:
            self.server_ref.stopping.wait(seconds if seconds > 0 else None)
            self.close_connection = True
            return True
        if kind is FaultKind.DISCONNECT:
            self.close_connection = True
            try:
                self.connection.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            return True
        time.sleep(seconds)  # delay, slow: then the normal answer
        return False

    def _authenticate(self, method: str) -> str | None:
        """The request's session (opened by valid Digest credentials), or None after a 401/503."""
        rws = self.server_ref
        cookies = _cookies(self.headers.get("Cookie", ""))
        abbcx = cookies.get("ABBCX")
        with rws._lock:
            if abbcx in rws.sessions and cookies.get("-http-session-") == rws.sessions[abbcx]:
                return abbcx
        header = self.headers.get("Authorization", "")
        if header.startswith("Digest ") and self._digest_ok(method, _parse_digest(header)):
            with rws._lock:
                if abbcx in rws.sessions:  # a known ABBCX with credentials (a WebSocket upgrade): fine
                    return abbcx
                if len(rws.sessions) >= rws.config.max_sessions:
                    full = True
                else:
                    full = False
                    abbcx = str(secrets.randbelow(10**9))
                    rws.sessions[abbcx] = f"1::http.session::{secrets.token_hex(8)}"
            if full:
                self._send_json(503, {"_embedded": {"status": {"code": -1073445859,
                                                               "msg": "too many active sessions"}}})
                return None
            assert abbcx is not None
            self._new_cookies = [f"-http-session-={rws.sessions[abbcx]}; path=/; httponly",
                                 f"ABBCX={abbcx}; path=/; httponly"]
            return abbcx
        nonce = secrets.token_hex(16)
        with rws._lock:
            rws.nonces.add(nonce)
        self._send(401, b"", "text/plain", extra={
            "WWW-Authenticate": f'Digest realm="{REALM}", qop="auth", nonce="{nonce}", '
                                f'opaque="{_md5(REALM)[:6]}", algorithm="MD5", stale="FALSE"'})
        return None

    def _digest_ok(self, method: str, fields: dict[str, str]) -> bool:
        cfg = self.server_ref.config
        with self.server_ref._lock:
            known = fields.get("nonce") in self.server_ref.nonces
        if not known or fields.get("username") != cfg.username or fields.get("realm") != REALM:
            return False
        ha1 = _md5(f"{cfg.username}:{REALM}:{cfg.password}")
        ha2 = _md5(f"{method}:{fields.get('uri', '')}")
        if fields.get("qop"):
            expected = _md5(f"{ha1}:{fields['nonce']}:{fields.get('nc', '')}:{fields.get('cnonce', '')}:"
                            f"{fields['qop']}:{ha2}")
        else:
            expected = _md5(f"{ha1}:{fields['nonce']}:{ha2}")
        return secrets.compare_digest(expected, fields.get("response", ""))

    def _base(self) -> str:
        return f"http://{self.server_ref.host}:{self.server_ref.port}/"

    def _send_json(self, status: int, payload: Any) -> None:
        self._send(status, json.dumps(payload).encode(), "application/json")

    def _send(self, status: int, payload: bytes, content_type: str, extra: dict[str, str] | None = None) -> None:
        try:
            self.send_response(status)
            if status != 204:
                self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(payload)))
            for cookie in getattr(self, "_new_cookies", []):
                self.send_header("Set-Cookie", cookie)
            self._new_cookies = []
            for key, value in (extra or {}).items():
                self.send_header(key, value)
            # Headers and body in one write: one segment for a small answer, as a controller sends it.
            buffer: list[bytes] = self._headers_buffer  # type: ignore[attr-defined]  # http.server's own
            buffer.append(b"\r\n")
            if payload and status != 204:
                buffer.append(payload)
            self.flush_headers()
        except OSError:
            self.close_connection = True

    # ----------------------------------------------------------------------------- WebSocket
    def _websocket(self, number: int) -> None:
        rws = self.server_ref
        with rws._lock:
            group = rws.subscriptions.get(number)
        key = self.headers.get("Sec-WebSocket-Key")
        if group is None or key is None or "websocket" not in self.headers.get("Upgrade", "").lower():
            raise RwsError(404, RWS_NOT_FOUND, f"no subscription group {number}")
        protocols = [p.strip() for p in self.headers.get("Sec-WebSocket-Protocol", "").split(",")]
        if SUBPROTOCOL not in protocols:
            raise RwsError(400, RWS_BAD_VALUE, f"the subscription protocol is {SUBPROTOCOL}")
        self.send_response(101, "Switching Protocols")
        self.send_header("Upgrade", "websocket")
        self.send_header("Connection", "Upgrade")
        self.send_header("Sec-WebSocket-Accept", accept_key(key))
        self.send_header("Sec-WebSocket-Protocol", SUBPROTOCOL)
        self.end_headers()
        self.wfile.flush()
        ws = WebSocketConnection(self.connection, self.rfile)  # type: ignore[arg-type]
        with rws._lock:
            group.sockets.append(ws)
        try:
            ws.serve()
        finally:
            with rws._lock:
                if ws in group.sockets:
                    group.sockets.remove(ws)
            self.close_connection = True

    # ----------------------------------------------------------------------------- resources
    def _route(self, method: str, path: str, query: dict[str, list[str]], body: bytes) -> tuple[int, bytes, str]:
        c = self.server_ref.controller
        form = parse_qs(body.decode("utf-8", errors="replace"), keep_blank_values=True)
        action = query.get("action", [""])[0]
        parts = [p for p in path.split("/") if p]
        if parts[:1] == ["fileservice"]:
            return self._files(method, "/".join(parts[1:]), body)
        if method == "GET":
            return 200, json.dumps(self._get(parts, query)).encode(), "application/json"
        if method == "POST" and parts == ["subscription"]:
            group = self.server_ref.subscribe(form)
            location = f"ws://{self.server_ref.host}:{self.server_ref.port}/poll/{group.number}"
            page = (f'<?xml version="1.0" encoding="utf-8"?><html xmlns="http://www.w3.org/1999/xhtml"><head>'
                    f'<title>Event</title><base href="{self._base()}"/></head><body><div class="state">'
                    f'<a href="{location}" rel="self">{html.escape(location)}</a>'
                    f'<a href="subscription/{group.number}" rel="group"></a></div></body></html>')
            return 201, page.encode(), "application/xhtml+xml;v=1.0"
        if method == "DELETE" and parts[:1] == ["subscription"]:
            with self.server_ref._lock:
                ended = self.server_ref.subscriptions.get(int(parts[1]))
                if ended is not None:
                    del self.server_ref.subscriptions[ended.number]
            for ws in ended.sockets if ended else []:
                ws.close()
            return 200, b"", "text/plain"
        if method != "POST":
            raise RwsError(405, RWS_NOT_FOUND, f"{method} {path} is not allowed")
        value = lambda name: form.get(name, [""])[0]
        if parts == ["rw", "rapid", "execution"]:
            if action == "start":
                c.start_execution(value("cycle") or "asis")
            elif action == "stop":
                c.stop_execution()
            elif action == "resetpp":
                c.resetpp()
            else:
                raise RwsError(400, RWS_BAD_VALUE, f"unknown execution action {action!r}")
        elif parts[:3] == ["rw", "rapid", "tasks"] and action in ("activate", "deactivate"):
            if parts[3:] not in (["T_ROB1"], ["logger"], ["error_reporter"]):
                raise RwsError(404, RWS_NOT_FOUND, f"task {'/'.join(parts[3:])} not found")
        elif parts == ["rw", "panel", "ctrlstate"] and action == "setctrlstate":
            c.set_controller_state(value("ctrl-state"))
        elif parts == ["rw", "panel", "speedratio"] and action == "setspeedratio":
            c.set_speedratio(float(value("speed-ratio")))
        elif parts[:3] == ["rw", "iosystem", "signals"] and action == "set":
            c.set_signal(parts[-1], float(value("lvalue")))
        elif parts[:5] == ["rw", "rapid", "symbol", "data", "RAPID"] and action == "set":
            c.set_symbol("/".join(parts[5:]), value("value"))
        elif parts[:2] == ["users", "rmmp"]:
            pass  # remote mastership: granted at once (there is no pendant to confirm it)
        else:
            raise RwsError(404, RWS_NOT_FOUND, f"no resource {path} for action {action!r}")
        return 204, b"", "application/json"

    def _files(self, method: str, path: str, body: bytes) -> tuple[int, bytes, str]:
        c = self.server_ref.controller
        if method == "PUT":
            c.write_file(path, body)
            return 201, b"", "text/plain"
        if method == "DELETE":
            c.delete_file(path)
            return 204, b"", "text/plain"
        if method != "GET":
            raise RwsError(405, RWS_NOT_FOUND, f"{method} is not allowed on files")
        try:
            return 200, c.read_file(path), "application/octet-stream"
        except RwsError:
            names = c.list_files(path)
            if not names and path.strip("/").upper() not in ("$TEMP", "$RAMDISK", "$HOME"):
                raise
            states = [{"_type": "fs-file", "_title": name, "fs-size": str(len(c.read_file(f"{path}/{name}")))}
                      for name in names]
            return 200, json.dumps(self._envelope("fileservice/" + path, states)).encode(), "application/json"

    def _envelope(self, base: str, states: list[dict[str, Any]]) -> dict[str, Any]:
        return {"_links": {"base": {"href": self._base() + base.strip("/") + "/"}},
                "_embedded": {"_state": states}}

    def _get(self, parts: list[str], query: dict[str, list[str]]) -> dict[str, Any]:
        c = self.server_ref.controller
        cfg = self.server_ref.config
        joined = "/".join(parts)
        state: list[dict[str, Any]]
        if joined == "rw/panel/ctrlstate":
            state = [{"_type": "pnl-ctrlstate", "_title": "ctrlstate", "ctrlstate": c.ctrlstate}]
        elif joined == "rw/panel/opmode":
            state = [{"_type": "pnl-opmode", "_title": "opmode", "opmode": c.opmode}]
        elif joined == "rw/panel/speedratio":
            state = [{"_type": "pnl-speedratio", "_title": "speedratio", "speedratio": format(c.speedratio, "g")}]
        elif joined == "rw/rapid/execution":
            state = [{"_type": "rap-execution", "_title": "execution", "ctrlexecstate": c.execution.state,
                      "cycle": c.execution.cycle}]
        elif joined == "rw/rapid/tasks":
            running = "started" if c.execution.state == "running" else "stopped"
            state = [
                {"_type": "rap-task-li", "_title": "T_ROB1", "name": "T_ROB1", "type": "norm", "taskstate": "link",
                 "excstate": running, "active": "On", "motiontask": "TRUE"},
                {"_type": "rap-task-li", "_title": "logger", "name": "logger", "type": "sstat", "taskstate": "link",
                 "excstate": "started", "active": "On", "motiontask": "FALSE"},
                {"_type": "rap-task-li", "_title": "error_reporter", "name": "error_reporter", "type": "sstat",
                 "taskstate": "link", "excstate": "started", "active": "On", "motiontask": "FALSE"}]
        elif joined.startswith("rw/rapid/symbol/data/RAPID/"):
            symbol = joined[len("rw/rapid/symbol/data/RAPID/"):]
            state = [{"_type": "rap-data", "_title": f"RAPID/{symbol}", "value": c.symbol(symbol)}]
        elif parts[:3] == ["rw", "iosystem", "signals"] and len(parts) > 3:
            kind, value = c.signal(parts[-1])
            text = str(int(value)) if float(value).is_integer() else format(value, ".9g")
            state = [{"_type": "ios-signal", "_title": "/".join(parts[3:]), "name": parts[-1], "type": kind,
                      "category": "", "lvalue": text, "lstate": "not simulated", "unitnm": parts[-2]
                      if len(parts) > 4 else "", "phstate": "valid", "pvalue": text, "quality": "good"}]
        elif parts[:2] == ["rw", "elog"] and len(parts) == 3:
            with c.lock:
                entries = list(c.elog[:cfg.event_log_page])  # the newest page, as RWS lists a domain
            state = [_elog_json(entry, parts[2]) for entry in entries]
        elif parts[:4] == ["rw", "motionsystem", "mechunits", "ROB_1"]:
            state = self._mechunit(parts[4:], query)
        elif joined == "rw/system":
            major, minor = cfg.rw_version.split(".")[:2]
            state = [{"_type": "sys-system", "_title": "system", "major": major, "minor": minor,
                      "name": cfg.system_name, "rwversion": cfg.rw_version, "sysid": "{9F3C1D7E-5A2B-4C8D-9E1F-"
                      "0A2B3C4D5E6F}", "starttm": "2026-01-05 T 08:00:00", "rwversionname": cfg.rw_version_name}]
        elif joined == "rw/system/robottype":
            state = [{"_type": "sys-robottype", "_title": "robottype", "robot-type": cfg.robot_type}]
        elif joined == "ctrl/identity":
            state = [{"_type": "ctrl-identity-info", "_title": "identity", "ctrl-name": cfg.controller_name,
                      "ctrl-type": "Real Controller", "ctrl-id": cfg.controller_id, "ctrl-mac": "00:80:f4:2a:51:34"}]
        elif joined == "ctrl/$RAMDISK":
            state = [{"_type": "ctrl-env", "_title": "$RAMDISK", "_value": cfg.ramdisk_path}]
        elif joined == "users/rmmp/poll":
            state = [{"_type": "user-rmmp-poll", "_title": "poll", "status": "GRANTED"}]
        elif joined == "logout":
            with self.server_ref._lock:
                self.server_ref.sessions.pop(_cookies(self.headers.get("Cookie", "")).get("ABBCX", ""), None)
            state = []
        else:
            raise RwsError(404, RWS_NOT_FOUND, f"no resource /{joined}")
        return self._envelope("/".join(parts[:-1]), state)

    def _mechunit(self, rest: list[str], query: dict[str, list[str]]) -> list[dict[str, Any]]:
        c = self.server_ref.controller
        if rest == ["jointtarget"]:
            joints = c.jointtarget()
            state = {"_type": "ms-jointtarget", "_title": "ROB_1",
                     **{f"rax_{i + 1}": format(float(v), ".9g") for i, v in enumerate(joints)},
                     **{f"eax_{a}": "9E+09" for a in "abcdef"}}
            return [state]
        if rest == ["robtarget"]:
            tool, wobj = query.get("tool", ["tool0"])[0], query.get("wobj", ["wobj0"])[0]
            trans, quat, conf = c.robtarget(tool, wobj, query.get("coordinate", ["Base"])[0])
            state = {"_type": "ms-robtargets", "_title": "ROB_1",
                     **{axis: format(float(v), ".9g") for axis, v in zip("xyz", trans)},
                     **{f"q{i + 1}": format(float(v), ".9g") for i, v in enumerate(quat)},
                     **{name: str(v) for name, v in zip(("cf1", "cf4", "cf6", "cfx"), conf)},
                     **{f"eax{a}": "9E+09" for a in "abcdef"}}
            return [state]
        if not rest:
            return [{"_type": "ms-mechunit", "_title": "ROB_1", "mode": "Activated", "activation-allowed": "1",
                     "drive-module": "1", "type": "TCPRobot", "task-name": "T_ROB1", "is-integrated-unit": "",
                     "has-integrated-unit": "", "axes": "6", "axes-total": "6"}]
        raise RwsError(404, RWS_NOT_FOUND, f"no resource /rw/motionsystem/mechunits/ROB_1/{'/'.join(rest)}")


def _cookies(header: str) -> dict[str, str]:
    out = {}
    for part in header.split(";"):
        key, _, value = part.strip().partition("=")
        if key:
            out[key] = value
    return out


def _elog_json(entry: Any, domain: str) -> dict[str, Any]:
    return {"_type": "elog-message-li", "_title": f"/rw/elog/{domain}/{entry.seqnum}",
            "_links": {"self": {"href": f"{domain}/{entry.seqnum}"}},
            "msgtype": str(entry.msgtype), "code": str(entry.code),
            "src-name": "RAPID" if entry.code >= 40000 else "MC0",
            "tstamp": entry.tstamp, "title": entry.title, "desc": entry.desc, "conseqs": entry.conseqs,
            "causes": entry.causes, "actions": entry.actions, "argc": str(len(entry.args)),
            "argv": [{"type": "STRING", "value": arg} for arg in entry.args]}


def event_xhtml(host: str, port: int, group: Subscription, key: str, path: str, value: str) -> str:
    """One subscription event: an XHTML page with the changed resource's ``<li>`` on one line."""
    v = html.escape(value)
    if key == "/rw/panel/ctrlstate":
        item = (f'<li class="pnl-ctrlstate-ev" title="ctrlstate"><a href="{path}" rel="self"></a>'
                f'<span class="ctrlstate">{v}</span></li>')
    elif key == "/rw/panel/opmode":
        item = (f'<li class="pnl-opmode-ev" title="opmode"><a href="{path}" rel="self"></a>'
                f'<span class="opmode">{v}</span></li>')
    elif key == "/rw/rapid/execution;ctrlexecstate":
        item = (f'<li class="rap-ctrlexecstate-ev" title="execution"><a href="{path}" rel="self"></a>'
                f'<span class="ctrlexecstate">{v}</span></li>')
    elif key == "/rw/elog/0":
        item = (f'<li class="elog-message-ev" title="message"><a href="/rw/elog/0/{v}?lang=en" rel="self"></a>'
                f'<span class="seqnum">{v}</span></li>')
    elif key.startswith("signal:"):
        title = path[len("/rw/iosystem/signals/"):-len(";state")]
        item = (f'<li class="ios-signalstate-ev" title="{html.escape(title)}"><a href="{path}" rel="self"></a>'
                f'<span class="lvalue">{v}</span><span class="lstate">not simulated</span>'
                f'<span class="quality">good</span></li>')
    else:
        title = path[len("/rw/rapid/symbol/data/RAPID/"):-len(";value")]
        item = (f'<li class="rap-data" title="{html.escape(title)}"><a href="{path}" rel="self"></a>'
                f'<span class="value">{v}</span></li>')
    return (f'<?xml version="1.0" encoding="utf-8"?><html xmlns="http://www.w3.org/1999/xhtml"><head>'
            f'<base href="http://{host}:{port}/"/></head><body><div class="state">'
            f'<a href="subscription/{group.number}" rel="group"></a> <ul>{item}</ul></div></body></html>')
