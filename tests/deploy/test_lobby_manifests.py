"""deploy/lobby/ and deploy/monitoring/: valid against their schemas, and consistent with the code.

Schemas, all offline:

- the Kubernetes kinds (StatefulSet, Service, PodDisruptionBudget, NetworkPolicy, Secret) against
  the Kubernetes API's own schemas as the package kubernetes-validate ships them (JSON Schema
  made from the API's OpenAPI definitions, Apache-2.0; a dev dependency), in their strict form
  (a field the API does not define is an error, as ``kubectl apply``'s strict field validation
  makes it), for Kubernetes :data:`KUBERNETES`;
- PodMonitor and PrometheusRule against the openAPIV3Schema of the Prometheus Operator's CRDs
  (tests/data/prometheus-operator/, v0.93.0, Apache-2.0), read as the API server reads a CRD
  schema (tests/deploy/test_agones_manifests.py's ``_kube_schema``).

Then what an operator relies on beyond the schemas: the lobby's arguments parse with ``haptic
lobby``'s own parser for every replica (after Kubernetes' ``$(VAR)`` expansion) and name this
replica among its peers; every file it reads is on a volume that holds it; the probes, Services,
PodDisruptionBudget, NetworkPolicy and PodMonitors select the pods and ports that exist; every
metric and label an alert reads is one the lobby or the room server exports (from a real
scrape), or Agones' documented ``agones_gameservers_count``; each alert's PromQL parses by
Prometheus' own grammar (@prometheus-io/lezer-promql, run with Node.js from tests/deploy/promql/,
installed by ``make test``). Not checked: admission (a cluster's policies, quotas), and what an
alert's query returns on real data.
"""

from __future__ import annotations

import copy
import json
import re
import shlex
import shutil
import subprocess
from pathlib import Path
from typing import Any

import jsonschema
import kubernetes_validate
import pytest
import yaml
from prometheus_client import generate_latest
from prometheus_client.parser import text_string_to_metric_families

from haptic_collab.cli import build_parser
from haptic_collab.server.app import ServerApp
from haptic_collab.server.lobby import AgonesAllocator, Lobby
from haptic_collab.server.lobby_limits import parse_proxies
from haptic_collab.server.lobby_peers import Peers
from haptic_collab.server.room import Room
from tests.deploy.test_agones_manifests import _OBJECT_META, _kube_schema
from tests.support.rooms import RecordingWorld

ROOT = Path(__file__).resolve().parents[2]
LOBBY = ROOT / "deploy" / "lobby"
MONITORING = ROOT / "deploy" / "monitoring"
FLEET = ROOT / "deploy" / "agones" / "fleet.yaml"
PROM_CRDS = ROOT / "tests" / "data" / "prometheus-operator"
#: The Kubernetes version the core kinds are checked against.
KUBERNETES = "1.33.0"


def docs(path: Path) -> list[dict[str, Any]]:
    return [d for d in yaml.safe_load_all(path.read_text()) if d]


def one(kind: str, name: str | None = None) -> dict[str, Any]:
    found = [
        d
        for p in (*sorted(LOBBY.glob("*.yaml")), *sorted(MONITORING.glob("*.yaml")))
        for d in docs(p)
        if d["kind"] == kind and (name is None or d["metadata"]["name"] == name)
    ]
    assert len(found) == 1, (kind, name, len(found))
    return found[0]


def all_manifests() -> list[tuple[str, dict[str, Any]]]:
    paths = [
        *sorted(LOBBY.glob("*.yaml")),
        *sorted((LOBBY / "examples").glob("*.yaml")),
        *sorted(MONITORING.glob("*.yaml")),
    ]
    return [
        (f"{p.relative_to(ROOT)}:{d['kind']}/{d['metadata']['name']}", d)
        for p in paths
        for d in docs(p)
    ]


def prometheus_schemas() -> dict[tuple[str, str], dict[str, Any]]:
    out = {}
    for path in sorted(PROM_CRDS.glob("*.yaml")):
        crd = yaml.safe_load(path.read_text())
        group, kind = crd["spec"]["group"], crd["spec"]["names"]["kind"]
        for version in crd["spec"]["versions"]:
            schema = copy.deepcopy(version["schema"]["openAPIV3Schema"])
            schema["properties"] = {
                **schema["properties"],
                "apiVersion": {"type": "string", "enum": [f"{group}/{version['name']}"]},
                "kind": {"type": "string", "enum": [kind]},
                "metadata": _OBJECT_META,
            }
            schema.setdefault("required", [])
            schema["required"] = sorted({*schema["required"], "apiVersion", "kind", "metadata"})
            out[f"{group}/{version['name']}", kind] = _kube_schema(schema)
    return out


MANIFESTS = all_manifests()


@pytest.mark.parametrize("manifest", [m for _, m in MANIFESTS], ids=[w for w, _ in MANIFESTS])
def test_every_manifest_is_valid_against_its_schema(manifest: dict[str, Any]) -> None:
    crds = prometheus_schemas()
    key = (manifest["apiVersion"], manifest["kind"])
    if key in crds:
        errors = sorted(
            jsonschema.Draft7Validator(crds[key]).iter_errors(manifest), key=lambda e: e.path
        )
        assert not errors, [f"{list(e.path)}: {e.message}" for e in errors]
    else:  # a Kubernetes kind: strict, as kubectl apply checks fields
        kubernetes_validate.validate(manifest, KUBERNETES, strict=True)


def test_the_schemas_catch_a_misspelt_field() -> None:
    sts = copy.deepcopy(one("StatefulSet"))
    sts["spec"]["template"]["spec"]["containers"][0]["readinessProbes"] = {}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(sts, KUBERNETES, strict=True)
    rule = copy.deepcopy(one("PrometheusRule"))
    rule["spec"]["groups"][0]["rules"][0]["expression"] = "up"
    schema = prometheus_schemas()[rule["apiVersion"], "PrometheusRule"]
    assert list(jsonschema.Draft7Validator(schema).iter_errors(rule))


def _expanded_args(container: dict[str, Any], pod_name: str, namespace: str) -> list[str]:
    """The container's args as Kubernetes expands ``$(VAR)`` of its env's field refs."""
    values = {"metadata.name": pod_name, "metadata.namespace": namespace}
    env = {e["name"]: values[e["valueFrom"]["fieldRef"]["fieldPath"]] for e in container["env"]}
    return [re.sub(r"\$\(([A-Z_]+)\)", lambda m: env[m.group(1)], a) for a in container["args"]]


def test_every_replica_parses_its_arguments_and_finds_itself_among_its_peers() -> None:
    sts = one("StatefulSet")
    (container,) = sts["spec"]["template"]["spec"]["containers"]
    replicas = sts["spec"]["replicas"]
    owners = set()
    for i in range(replicas):
        pod = f"{sts['metadata']['name']}-{i}"
        args = build_parser().parse_args(_expanded_args(container, pod, "labs"))
        assert args.func.__name__ == "_cmd_lobby", shlex.join(container["args"])
        peers = Peers.of(args.peer, args.peer_self)  # raises unless this replica is listed
        assert len(peers.urls) == replicas  # one --peer per replica: keep them in step
        for url in peers.urls:  # each a pod of this StatefulSet under its headless Service
            assert re.fullmatch(
                rf"http://{sts['metadata']['name']}-\d+\.{sts['spec']['serviceName']}\.labs\.svc:"
                rf"{args.port}",
                url,
            ), url
        assert args.agones_namespace == "labs"
        assert parse_proxies(args.trusted_proxy)
        owners.add(peers.owner("anatomy-1"))
    assert len(owners) == 1  # every replica agrees on who places a name


def _mounted(pod: dict[str, Any], container: dict[str, Any]) -> dict[str, str]:
    """File path -> ``secret/KEY`` of every file the container's Secret volumes hold."""
    volumes = {v["name"]: v for v in pod["volumes"]}
    out = {}
    for mount in container["volumeMounts"]:
        secret = volumes[mount["name"]]["secret"]
        items = secret.get("items")
        keys = [(i["key"], i["path"]) for i in items] if items else None
        if keys is None:  # the whole Secret: its keys are not known here
            out[mount["mountPath"] + "/*"] = secret["secretName"] + "/*"
        else:
            for key, path in keys:
                out[f"{mount['mountPath']}/{path}"] = f"{secret['secretName']}/{key}"
    return out


def test_every_file_the_lobby_reads_is_on_a_volume_that_holds_it() -> None:
    sts = one("StatefulSet")
    pod = sts["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    args = build_parser().parse_args(_expanded_args(container, "haptic-lobby-0", "labs"))
    mounted = _mounted(pod, container)
    example = docs(LOBBY / "examples" / "allocator-client-secret.yaml")[0]
    fleet = docs(FLEET)[0]
    fleet_pod = fleet["spec"]["template"]["spec"]["template"]["spec"]
    fleet_secret = next(v["secret"]["secretName"] for v in fleet_pod["volumes"] if "secret" in v)
    for path in (
        args.token_secret_file,
        args.token_file,
        args.metrics_token_file,
        args.agones_ca,
        args.agones_client_cert,
        args.agones_client_key,
    ):
        folder, _, name = path.rpartition("/")
        source = mounted.get(path) or mounted.get(folder + "/*")
        assert source is not None, f"{path} is on no volume"
        secret, _, key = source.partition("/")
        if secret == example["metadata"]["name"]:  # the allocator's: the example's keys
            assert name in example["stringData"], (path, sorted(example["stringData"]))
        elif secret == fleet_secret:  # shared with the Fleet: the same Secret and keys
            assert key in ("token_secret", "metrics_token"), key
        else:
            assert secret == "haptic-lobby-tokens" and name == "lobby_tokens", source
    assert example["type"] == "Opaque"


def test_users_and_prometheus_speak_tls_to_the_fleets_game_port_as_it_serves_it() -> None:
    """The Fleet's servers serve TLS on the game port (``--tls-cert``): the lobby hands users
    ``wss://`` URLs and ``https://`` viewer pages for them, and the PodMonitor scrapes that
    port over https (a plain ws:// or http:// to it fails the TLS handshake)."""
    fleet = docs(FLEET)[0]
    (server,) = fleet["spec"]["template"]["spec"]["template"]["spec"]["containers"]
    tls = build_parser().parse_args(server["args"]).tls_cert is not None
    assert tls  # what deploy/agones/fleet.yaml says now; the rest holds either way
    sts = one("StatefulSet")
    (container,) = sts["spec"]["template"]["spec"]["containers"]
    args = build_parser().parse_args(_expanded_args(container, "haptic-lobby-0", "labs"))
    backend = AgonesAllocator("http://allocator.invalid", scheme=args.public_scheme)
    answer = {"gameServerName": "gs-1", "address": "203.0.113.5", "ports": [{"port": 7005}]}
    placed = backend.placement("lab", answer)
    assert placed.ws_base == ("wss" if tls else "ws") + "://203.0.113.5:7005"
    assert placed.http_base == ("https" if tls else "http") + "://203.0.113.5:7005"
    (game,) = one("PodMonitor", "haptic-collab")["spec"]["podMetricsEndpoints"]
    assert game.get("scheme", "http") == ("https" if tls else "http")


def test_services_budget_policy_and_probes_select_the_lobby_s_pods_and_port() -> None:
    sts = one("StatefulSet")
    labels = sts["spec"]["template"]["metadata"]["labels"]
    (container,) = sts["spec"]["template"]["spec"]["containers"]
    port = next(p for p in container["ports"] if p["name"] == "http")
    args = build_parser().parse_args(_expanded_args(container, "haptic-lobby-0", "labs"))
    assert port["containerPort"] == args.port
    for probe in ("readinessProbe", "livenessProbe"):
        assert container[probe]["httpGet"] == {"path": "/healthz", "port": "http"}

    def selects(selector: dict[str, str]) -> bool:
        return all(labels.get(k) == v for k, v in selector.items())

    users, peers = one("Service", "haptic-lobby"), one("Service", "haptic-lobby-peers")
    for svc in (users, peers):
        assert selects(svc["spec"]["selector"])
        assert [p["targetPort"] for p in svc["spec"]["ports"]] == ["http"]
    assert peers["metadata"]["name"] == sts["spec"]["serviceName"]
    assert peers["spec"]["clusterIP"] == "None"  # headless: a DNS name per pod
    pdb = one("PodDisruptionBudget")
    assert selects(pdb["spec"]["selector"]["matchLabels"])
    assert pdb["spec"]["maxUnavailable"] == 1
    policy = one("NetworkPolicy")
    assert selects(policy["spec"]["podSelector"]["matchLabels"])
    assert [p["port"] for r in policy["spec"]["ingress"] for p in r["ports"]] == [args.port]
    egress = {(p["port"], p["protocol"]) for r in policy["spec"]["egress"] for p in r["ports"]}
    assert {(53, "UDP"), (args.port, "TCP"), (8443, "TCP")} <= egress


def test_the_pod_monitors_scrape_the_lobby_and_the_fleet_with_the_metrics_token() -> None:
    sts = one("StatefulSet")
    lobby_monitor = one("PodMonitor", "haptic-lobby")
    labels = sts["spec"]["template"]["metadata"]["labels"]
    assert all(labels[k] == v for k, v in lobby_monitor["spec"]["selector"]["matchLabels"].items())
    (endpoint,) = lobby_monitor["spec"]["podMetricsEndpoints"]
    assert endpoint["port"] == "http" and endpoint["path"] == "/metrics"
    fleet = docs(FLEET)[0]
    fleet_monitor = one("PodMonitor", "haptic-collab")
    # Agones labels every pod of a Fleet's GameServers with agones.dev/fleet: NAME
    assert fleet_monitor["spec"]["selector"]["matchLabels"] == {
        "agones.dev/fleet": fleet["metadata"]["name"]
    }
    (game,) = fleet_monitor["spec"]["podMetricsEndpoints"]
    assert game["portNumber"] in [
        p["containerPort"] for p in fleet["spec"]["template"]["spec"]["ports"]
    ]
    pod = sts["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    mounted = _mounted(pod, container)
    for ep in (endpoint, game):
        cred = ep["authorization"]["credentials"]
        assert f"{cred['name']}/{cred['key']}" in mounted.values()  # the token both serve


def exported_metrics() -> dict[str, set[str]]:
    """Metric name -> label names, from a scrape of a lobby and of a room server (not started)."""
    lobby = Lobby(AgonesAllocator("http://127.0.0.1:9"), b"x" * 32, port=0)
    lobby.answered[200] = 1
    lobby.counts["rooms_refused", "503"] = 1
    lobby.counts["connections_refused", "address"] = 1
    lobby.backend.answers["429"] = 1  # type: ignore[attr-defined]
    app = ServerApp(Room(RecordingWorld(), 20.0), "127.0.0.1", 0)
    out: dict[str, set[str]] = {}
    for registry in (lobby.metrics_registry, app.metrics_registry):
        for family in text_string_to_metric_families(generate_latest(registry).decode()):
            for s in family.samples:
                out.setdefault(s.name, set()).update(s.labels)
    return out


#: Agones controller metrics the rules read (Agones' metrics reference): name -> labels.
AGONES_METRICS = {"agones_gameservers_count": {"type", "fleet_name", "namespace"}}
#: The alerts issue 78 asks for, by the metric each reads.
WANTED = {
    "haptic_room_tick_seconds_bucket": "tick p99",
    "haptic_room_overruns_total": "overruns",
    "haptic_lobby_rooms_refused_total": "refused rooms",
    "agones_gameservers_count": "Unhealthy GameServers",
    "haptic_lobby_allocator_answers_total": "allocation 429s",
}


def test_every_alert_reads_metrics_and_labels_that_are_exported() -> None:
    exported = {**exported_metrics(), **AGONES_METRICS}
    target = {"namespace", "pod", "le"}  # added by the scrape, or the histogram's own
    rule = one("PrometheusRule")
    read: set[str] = set()
    for group in rule["spec"]["groups"]:
        for r in group["rules"]:
            expr = r["expr"]
            assert expr.count("(") == expr.count(")") and expr.count("{") == expr.count("}")
            for name in re.findall(r"\b((?:haptic|agones|process)_[a-z_]+)\b", expr):
                assert name in exported, (r["alert"], name)
                read.add(name)
            for name, matchers in re.findall(r"\b([a-z_]+)\{([^}]*)\}", expr):
                for label in re.findall(r"(\w+)\s*(?:=~|!~|!=|=)", matchers):
                    assert label in exported[name] | target, (r["alert"], name, label)
            for label in re.findall(r"\$labels\.(\w+)", str(r.get("annotations"))):
                assert label in target | {"room", "fleet_name"}, (r["alert"], label)
    assert set(WANTED) <= read, {WANTED[m] for m in set(WANTED) - read}
    # the allocation alert is on the 429s, the refused-rooms alert on capacity refusals
    exprs = {r["alert"]: r["expr"] for g in rule["spec"]["groups"] for r in g["rules"]}
    assert 'code="429"' in exprs["HapticAllocationExhausted"]
    assert 'type="Unhealthy"' in exprs["HapticGameServersUnhealthy"]


PROMQL = ROOT / "tests" / "deploy" / "promql"


def promql_errors(exprs: dict[str, str]) -> dict[str, list[str]]:
    """Syntax errors of each PromQL expression, by Prometheus' grammar (tests/deploy/promql)."""
    node = shutil.which("node")
    if node is None or not (PROMQL / "node_modules" / "@prometheus-io").is_dir():
        pytest.skip("PromQL grammar not installed: make test (or npm ci in tests/deploy/promql)")
    done = subprocess.run(
        [node, str(PROMQL / "check.mjs")],
        input=json.dumps(exprs),
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    return json.loads(done.stdout)  # type: ignore[no-any-return]


def test_every_alert_expression_parses_as_promql() -> None:
    rule = one("PrometheusRule")
    exprs = {r["alert"]: r["expr"] for g in rule["spec"]["groups"] for r in g["rules"]}
    assert promql_errors(exprs) == {name: [] for name in exprs}
    # the check has teeth: a missing bracket and a doubled operator are errors
    broken = promql_errors({"a": "sum(rate(x_total[5m])", "b": "rate(x_total[5m]) >> 1"})
    assert all(broken.values()), broken
