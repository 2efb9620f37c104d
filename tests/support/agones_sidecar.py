"""A stand-in for the Agones SDK sidecar's REST gateway, built from Agones' swagger files.

No Agones SDK server can run here, so the tests start this one: an HTTP server on loopback that
serves the paths of tests/data/agones/sdk.swagger.json and beta.swagger.json, validates every
request body against the swagger's schema for it (jsonschema, draft 4 as Swagger 2.0 uses, with
int64 values as decimal strings), answers as the sidecar does (the documented answer schemas,
checked too; gRPC errors as ``{"code", "message", "details"}`` with the gateway's HTTP statuses)
and records every call.

Two deliberate readings of the swagger files:

- A body parameter bound to one field of the request (``counterUpdateRequest``, ``list``) lists
  that field's own name as ``required`` inside the body schema: that is how grpc-gateway's
  generator marks the binding, and the sidecar takes the field's properties as the body. The
  stand-in drops that one ``required`` entry.
- The stand-in refuses properties the schema does not name (``additionalProperties: false``
  added to every request object schema), where the gateway may ignore them: a misspelt field
  (``countdiff``) fails a test instead of silently doing nothing.

State follows the SDK server's source (Agones' pkg/sdkserver/sdkserver.go, commit b19d5fe,
Apache-2.0; the facts used are in tests/data/agones/sdkserver-errors.md with the licence in
tests/data/agones/LICENSE): Ready sets ``status.state`` Ready, Shutdown sets Shutdown, Allocate
and :meth:`Sidecar.allocate` (the allocator) set Allocated. Lists and counters answer their
refusals as the real sidecar does: plain Go errors (gRPC code Unknown, 2), which its REST gateway
sends as HTTP 500 with the Go text as ``message``: ``AddListValue`` checks the capacity *before*
the value ("out of range. No available capacity. ..." even for a value already there, else
"already exists. Value: V already in List: L"), ``RemoveListValue`` answers "not found: value V
not in list L", an undeclared list "list not found: L", an undeclared counter "counter not
found: C", a count outside [0, capacity] "out of range. Count must be within range
[0,Capacity]. ...". Labels are checked with real gRPC codes (InvalidArgument, HTTP 400): they
must be valid Kubernetes label values and names once prefixed ``agones.dev/sdk-``.

:meth:`Sidecar.hold` makes the answers to one path wait until the test lets them go, as a slow
sidecar's would.
"""

from __future__ import annotations

import copy
import json
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import jsonschema

DATA = Path(__file__).resolve().parents[1] / "data" / "agones"
LABEL_PREFIX = "agones.dev/sdk-"
_LABEL_VALUE = re.compile(r"^(([A-Za-z0-9][-A-Za-z0-9_.]*)?[A-Za-z0-9])?$")
_LABEL_NAME = re.compile(r"^([A-Za-z0-9][-A-Za-z0-9_.]*)?[A-Za-z0-9]$")

#: gRPC status codes and the HTTP statuses grpc-gateway maps them to. The SDK server returns
#: its list and counter refusals as plain Go errors, which gRPC sends as UNKNOWN (HTTP 500).
UNKNOWN, NOT_FOUND, INVALID_ARGUMENT = 2, 5, 3
_HTTP = {UNKNOWN: 500, NOT_FOUND: 404, INVALID_ARGUMENT: 400}

_FORMATS = jsonschema.FormatChecker()


@_FORMATS.checks("int64", raises=ValueError)
def _int64(value: object) -> bool:
    if isinstance(value, str):  # proto3 JSON: int64 as a decimal string
        if not re.fullmatch(r"-?[0-9]+", value):
            raise ValueError(f"{value!r} is not an int64 decimal string")
        return -(2**63) <= int(value) < 2**63
    return True  # the schema's type says what else is allowed


class _GrpcError(Exception):
    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass
class Call:
    """One request the stand-in received."""

    seq: int
    t: float  #: time.monotonic() on arrival [s]
    method: str
    path: str
    body: Any
    status: int = 0
    errors: list[str] = field(default_factory=list)  #: schema violations of the request


@dataclass
class _Route:
    method: str
    template: str
    regex: re.Pattern[str]
    params: list[str]
    body: dict[str, Any] | None  # strict request schema, with the spec's definitions
    answer: dict[str, Any] | None


def _strict(schema: Any) -> Any:
    """A copy of a request schema that refuses properties it does not name."""
    if isinstance(schema, dict):
        out = {k: _strict(v) for k, v in schema.items()}
        if out.get("type") == "object" and "additionalProperties" not in out:
            out["additionalProperties"] = False
        return out
    if isinstance(schema, list):
        return [_strict(v) for v in schema]
    return schema


def load_routes() -> list[_Route]:
    """Every operation of the two swagger files, with its request and answer schemas."""
    routes = []
    for name in ("sdk.swagger.json", "beta.swagger.json"):
        spec = json.loads((DATA / name).read_text())
        defs = _strict(spec["definitions"])
        loose_defs = spec["definitions"]
        for template, ops in spec["paths"].items():
            params = re.findall(r"{([^}]+)}", template)
            pattern = re.escape(template)
            for p in params:
                pattern = pattern.replace(re.escape("{" + p + "}"), "([^/:]+)")
            for method, op in ops.items():
                body = None
                for param in op.get("parameters", []):
                    if param["in"] != "body":
                        continue
                    schema = copy.deepcopy(param["schema"])
                    props = schema.get("properties", {})
                    req = [
                        r for r in schema.get("required", []) if r in props or r != param["name"]
                    ]
                    if "required" in schema:
                        schema["required"] = req
                    body = {**_strict(schema), "definitions": defs}
                answer = op["responses"]["200"].get("schema")
                routes.append(
                    _Route(
                        method.upper(),
                        template,
                        re.compile(f"^{pattern}$"),
                        params,
                        body,
                        None if answer is None else {**answer, "definitions": loose_defs},
                    )
                )
    return routes


class Sidecar:
    """The stand-in sidecar on ``127.0.0.1:port`` (0: a free port); a context manager.

    Parameters
    ----------
    port : int
    lists, counters : dict
        The GameServer's lists ``{name: capacity}`` and counters ``{name: capacity}`` as a
        Fleet's ``spec.template.spec.lists`` / ``counters`` would declare them.
    """

    def __init__(
        self,
        port: int = 0,
        lists: dict[str, int] | None = None,
        counters: dict[str, int] | None = None,
    ) -> None:
        self.routes = load_routes()
        self.calls: list[Call] = []
        self.state = "Scheduled"
        self.labels: dict[str, str] = {}
        self.lists = {n: {"capacity": c, "values": []} for n, c in (lists or {}).items()}
        self.counters = {n: {"capacity": c, "count": 0} for n, c in (counters or {}).items()}
        self._cond = threading.Condition()
        self._holds: dict[str, threading.Event] = {}
        #: Requests waiting in :meth:`hold`, by path.
        self.held: dict[str, int] = {}
        sidecar = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args: Any) -> None:  # quiet
                pass

            def _any(self) -> None:
                sidecar._serve(self)

            do_GET = do_POST = do_PUT = do_PATCH = do_DELETE = _any

        self._http = ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self._http.daemon_threads = True
        self.port = int(self._http.server_address[1])
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> Sidecar:
        self._thread = threading.Thread(target=self._http.serve_forever, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._http.shutdown()
        self._http.server_close()

    # ------------------------------------------------------------------ for the tests
    def allocate(self, add_values: dict[str, list[str]] | None = None) -> None:
        """What a GameServerAllocation does: Ready becomes Allocated, and its
        ``lists.NAME.addValues`` are appended (a value already there is ignored, values past
        the capacity are dropped, as tests/support/agones_allocator.py does)."""
        with self._cond:
            self.state = "Allocated"
            for name, values in (add_values or {}).items():
                lst = self.lists[name]
                for value in values:
                    if value not in lst["values"] and len(lst["values"]) < lst["capacity"]:
                        lst["values"].append(value)
            self._cond.notify_all()

    def hold(self, path: str) -> threading.Event:
        """Keep every answer to ``path`` waiting until the returned event is set (60 s at most);
        :attr:`held` counts the requests that waited so."""
        gate = threading.Event()
        with self._cond:
            self._holds[path] = gate
        return gate

    def of(self, method: str, path: str) -> list[Call]:
        """The calls of one method and path, in order."""
        with self._cond:
            return [c for c in self.calls if c.method == method and c.path == path]

    def wait(self, predicate: Callable[[], bool], timeout_s: float = 30.0) -> bool:
        """Wait until ``predicate()`` (checked after every call and every 0.1 s) holds."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not predicate():
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(min(left, 0.1))
        return True

    # ------------------------------------------------------------------ serving
    def _serve(self, h: BaseHTTPRequestHandler) -> None:
        length = int(h.headers.get("Content-Length") or 0)
        raw = h.rfile.read(length) if length else b""
        path = h.path.split("?", 1)[0]
        with self._cond:
            gate = self._holds.get(path)
            if gate is not None:
                self.held[path] = self.held.get(path, 0) + 1
                self._cond.notify_all()
        if gate is not None:
            gate.wait(60.0)
        with self._cond:
            call = Call(len(self.calls), time.monotonic(), h.command, path, None)
            self.calls.append(call)
            status, answer = self._answer(call, raw, h.headers.get("Content-Type", ""))
            call.status = status
            self._cond.notify_all()
        data = json.dumps(answer).encode()
        h.send_response(status)
        h.send_header("Content-Type", "application/json")
        h.send_header("Content-Length", str(len(data)))
        h.end_headers()
        h.wfile.write(data)

    def _answer(self, call: Call, raw: bytes, ctype: str) -> tuple[int, Any]:
        for route in self.routes:
            m = route.regex.match(call.path)
            if m is None:
                continue
            if route.method != call.method:
                continue
            if route.body is not None:
                if not ctype.startswith("application/json"):
                    call.errors.append(f"Content-Type {ctype!r}, not application/json")
                try:
                    call.body = json.loads(raw)
                except ValueError:
                    call.errors.append("the body is not JSON")
                else:
                    v = jsonschema.Draft4Validator(route.body, format_checker=_FORMATS)
                    call.errors += [e.message for e in v.iter_errors(call.body)]
                if call.errors:
                    return 400, _status(INVALID_ARGUMENT, "; ".join(call.errors))
            try:
                answer = self._do(
                    route.template,
                    call.method,
                    dict(zip(route.params, m.groups(), strict=True)),
                    call.body,
                )
            except _GrpcError as exc:
                return _HTTP[exc.code], _status(exc.code, str(exc))
            if route.answer is not None:  # the stand-in answers what the swagger says
                jsonschema.Draft4Validator(route.answer, format_checker=_FORMATS).validate(answer)
            return 200, answer
        call.errors.append("no such path and method in the swagger files")
        return 404, _status(NOT_FOUND, f"Not Found: {call.method} {call.path}")

    def _do(self, template: str, method: str, params: dict[str, str], body: Any) -> Any:
        if template == "/ready":
            self.state = "Ready" if self.state != "Allocated" else self.state
            return {}
        if template == "/health":
            return {}
        if template == "/allocate":  # the SDK's self-allocation
            self.state = "Allocated"
            return {}
        if template == "/shutdown":
            self.state = "Shutdown"
            return {}
        if template == "/metadata/label":
            key, value = body.get("key", ""), body.get("value", "")
            name = LABEL_PREFIX + key
            if not (_LABEL_NAME.match(key) and len(key) <= 63 - len("sdk-")):
                raise _GrpcError(INVALID_ARGUMENT, f"invalid label key {name!r}")
            if not (len(value) <= 63 and _LABEL_VALUE.match(value)):
                raise _GrpcError(INVALID_ARGUMENT, f"invalid label value {value!r}")
            self.labels[name] = value
            return {}
        if template == "/gameserver":
            return self._game_server()
        if template.startswith("/v1beta1/lists/"):
            return self._list(template, params, body)
        if template.startswith("/v1beta1/counters/"):
            return self._counter(method, params, body)
        raise _GrpcError(INVALID_ARGUMENT, f"the stand-in does not implement {template}")

    def _game_server(self) -> dict[str, Any]:
        return {
            "object_meta": {
                "name": "stand-in",
                "namespace": "default",
                "labels": dict(self.labels),
            },
            "status": {
                "state": self.state,
                "address": "127.0.0.1",
                "counters": {
                    n: {"count": str(c["count"]), "capacity": str(c["capacity"])}
                    for n, c in self.counters.items()
                },
                "lists": {
                    n: {"capacity": str(v["capacity"]), "values": list(v["values"])}
                    for n, v in self.lists.items()
                },
            },
        }

    def _list(self, template: str, params: dict[str, str], body: Any) -> dict[str, Any]:
        name = params.get("name") or params.get("list.name", "")
        lst = self.lists.get(name)
        if lst is None:  # GetList
            raise _GrpcError(UNKNOWN, f"list not found: {name}")
        value, values = body.get("value") if body else None, lst["values"]
        if template.endswith(":addValue"):  # AddListValue: capacity first, then the value
            if lst["capacity"] <= len(values):
                raise _GrpcError(
                    UNKNOWN,
                    "out of range. No available capacity. Current Capacity: "
                    f"{lst['capacity']}, List Size: {len(values)}",
                )
            if value in values:
                raise _GrpcError(UNKNOWN, f"already exists. Value: {value} already in List: {name}")
            values.append(value)
        elif template.endswith(":removeValue"):  # RemoveListValue
            if value not in values:
                raise _GrpcError(UNKNOWN, f"not found: value {value} not in list {name}")
            values.remove(value)
        elif body is not None:
            raise _GrpcError(INVALID_ARGUMENT, "the stand-in does not implement UpdateList")
        return {"name": name, "capacity": str(lst["capacity"]), "values": list(lst["values"])}

    def _counter(self, method: str, params: dict[str, str], body: Any) -> dict[str, Any]:
        name = params.get("name") or params.get("counterUpdateRequest.name", "")
        c = self.counters.get(name)
        if c is None:
            raise _GrpcError(UNKNOWN, f"counter not found: {name}")
        if method == "PATCH":  # UpdateCounter
            capacity = int(body.get("capacity", c["capacity"]))
            count = int(body["count"]) if "count" in body else c["count"]
            count += int(body.get("countDiff", 0))
            if not 0 <= count <= capacity:
                raise _GrpcError(
                    UNKNOWN,
                    "out of range. Count must be within range [0,Capacity]. Found Count: "
                    f"{count}, Capacity: {capacity}",
                )
            c["count"], c["capacity"] = count, capacity
        return {"name": name, "count": str(c["count"]), "capacity": str(c["capacity"])}


def _status(code: int, message: str) -> dict[str, Any]:
    return {"code": code, "message": message, "details": []}
