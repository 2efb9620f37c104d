"""deploy/agones/: every manifest is valid against the schema of its Agones kind.

The schemas are the openAPIV3Schema of Agones' CustomResourceDefinitions (Fleet and
FleetAutoscaler; tests/data/agones/fleet-crds.yaml.gz, the first two documents of Agones'
install.yaml, Apache-2.0). The Fleet's schema carries the whole Kubernetes pod template, so the
pod spec is checked too. Two things Kubernetes adds to a CRD's schema are added here: the
``apiVersion``/``kind``/``metadata`` every object has, and strict field validation (what
``kubectl apply`` does by default since Kubernetes 1.27: a field the schema does not name is an
error, except under ``x-kubernetes-preserve-unknown-fields``). ``nullable`` is read as allowing
null. No cluster is needed: this is the schema check the API server makes, not admission.

The ConfigMap (the servers' configuration file) and the PersistentVolumeClaim (the snapshot
volume) are core kinds with no CRD: their schemas, :data:`CONFIGMAP_SCHEMA` and
:data:`PVC_SCHEMA`, are written here from the Kubernetes API reference, "ConfigMap" and
"PersistentVolumeClaim" (``v1``, https://kubernetes.io/docs/reference/kubernetes-api/
config-and-storage-resources/config-map-v1/ and .../persistent-volume-claim-v1/, Kubernetes
1.31; CC BY 4.0, The Kubernetes Authors): the ConfigMap's four fields and the key pattern of
``data``; the claim's ``spec`` fields (access modes by their enum, the storage request). The Secret the fleet mounts is made by ``kubectl create secret``
(its values are not committed), so there is no Secret manifest to check: the test checks that
the fleet reads each file from the Secret volume.
"""

from __future__ import annotations

import argparse
import copy
import gzip
import shlex
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from haptic_collab.cli import build_parser
from haptic_collab.cli.run import _server_options
from haptic_collab.server.agones import ROOMS_LIST, USERS_COUNTER, AgonesOptions
from haptic_collab.server.config import apply_server_config
from haptic_collab.server.main import RoomTemplates, build_agones, build_room
from haptic_collab.server.urls import DEFAULT_ROOM
from haptic_collab.shared.protocol import LinkConditions

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy" / "agones"
CRDS = ROOT / "tests" / "data" / "agones" / "fleet-crds.yaml.gz"

#: What the API server knows of every object besides its CRD's schema (ObjectMeta, in part).
_OBJECT_META = {
    "type": "object",
    "properties": {
        "name": {
            "type": "string",
            "pattern": r"^[a-z0-9]([-a-z0-9.]*[a-z0-9])?$",
            "maxLength": 253,
        },
        "namespace": {"type": "string"},
        "labels": {"type": "object", "additionalProperties": {"type": "string"}},
        "annotations": {"type": "object", "additionalProperties": {"type": "string"}},
    },
    "additionalProperties": False,
}


#: ConfigMap v1 (Kubernetes API reference; see the module): ``data`` maps a key (a file name
#: when mounted) to text, ``binaryData`` to base64 bytes, ``immutable`` forbids updates.
_CONFIGMAP_KEY = r"^[-._a-zA-Z0-9]+$"
CONFIGMAP_SCHEMA = {
    "type": "object",
    "properties": {
        "apiVersion": {"type": "string", "enum": ["v1"]},
        "kind": {"type": "string", "enum": ["ConfigMap"]},
        "metadata": {**_OBJECT_META, "required": ["name"]},
        "data": {
            "type": "object",
            "propertyNames": {"pattern": _CONFIGMAP_KEY, "maxLength": 253},
            "additionalProperties": {"type": "string"},
        },
        "binaryData": {
            "type": "object",
            "propertyNames": {"pattern": _CONFIGMAP_KEY, "maxLength": 253},
            "additionalProperties": {"type": "string", "contentEncoding": "base64"},
        },
        "immutable": {"type": "boolean"},
    },
    "required": ["apiVersion", "kind", "metadata"],
    "additionalProperties": False,
}


#: PersistentVolumeClaim v1 (Kubernetes API reference; see the module): the fields of ``spec``.
_QUANTITY = {"type": "string", "pattern": r"^[0-9]+(\.[0-9]+)?(m|k|Ki|Mi|Gi|Ti|Pi|Ei|M|G|T|P|E)?$"}
PVC_SCHEMA = {
    "type": "object",
    "properties": {
        "apiVersion": {"type": "string", "enum": ["v1"]},
        "kind": {"type": "string", "enum": ["PersistentVolumeClaim"]},
        "metadata": {**_OBJECT_META, "required": ["name"]},
        "spec": {
            "type": "object",
            "properties": {
                "accessModes": {
                    "type": "array",
                    "items": {
                        "enum": [
                            "ReadWriteOnce",
                            "ReadOnlyMany",
                            "ReadWriteMany",
                            "ReadWriteOncePod",
                        ]
                    },
                },
                "resources": {
                    "type": "object",
                    "properties": {
                        "requests": {"type": "object", "additionalProperties": _QUANTITY},
                        "limits": {"type": "object", "additionalProperties": _QUANTITY},
                    },
                    "additionalProperties": False,
                },
                "storageClassName": {"type": "string"},
                "volumeMode": {"enum": ["Filesystem", "Block"]},
                "volumeName": {"type": "string"},
                "volumeAttributesClassName": {"type": "string"},
                "selector": {"type": "object"},
                "dataSource": {"type": "object"},
                "dataSourceRef": {"type": "object"},
            },
            "additionalProperties": False,
        },
    },
    "required": ["apiVersion", "kind", "metadata", "spec"],
    "additionalProperties": False,
}


def _kube_schema(node: Any) -> Any:
    """An openAPIV3Schema read as Kubernetes reads it, as a JSON Schema."""
    if isinstance(node, list):
        return [_kube_schema(n) for n in node]
    if not isinstance(node, dict):
        return node
    out = {k: _kube_schema(v) for k, v in node.items()}
    if out.get("type") == "object" and "properties" in out:
        if (
            not out.get("x-kubernetes-preserve-unknown-fields")
            and "additionalProperties" not in out
        ):
            out["additionalProperties"] = False
    if out.pop("nullable", False) and isinstance(out.get("type"), str):
        out["type"] = [out["type"], "null"]
    return out


def crd_schemas() -> dict[tuple[str, str], dict[str, Any]]:
    """``{(apiVersion, kind): JSON Schema}`` of every served version of the CRDs."""
    out = {}
    with gzip.open(CRDS, "rt") as f:
        for crd in yaml.safe_load_all(f):
            if not crd or crd.get("kind") != "CustomResourceDefinition":
                continue
            group, kind = crd["spec"]["group"], crd["spec"]["names"]["kind"]
            for version in crd["spec"]["versions"]:
                schema = copy.deepcopy(version["schema"]["openAPIV3Schema"])
                schema["properties"] = {
                    "apiVersion": {"type": "string", "enum": [f"{group}/{version['name']}"]},
                    "kind": {"type": "string", "enum": [kind]},
                    "metadata": _OBJECT_META,
                    **schema["properties"],
                }
                schema["required"] = ["apiVersion", "kind", "metadata", "spec"]
                out[(f"{group}/{version['name']}", kind)] = _kube_schema(schema)
    return out


def errors(doc: dict[str, Any], schemas: dict[tuple[str, str], dict[str, Any]]) -> list[str]:
    schema = schemas.get((doc.get("apiVersion"), doc.get("kind")))
    if schema is None:
        return [f"no schema for {doc.get('apiVersion')} {doc.get('kind')}"]
    validator = jsonschema.Draft7Validator(schema)
    return [
        f"{'.'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(doc)
    ]


def manifests() -> dict[str, dict[str, Any]]:
    """``{kind: document}`` of every YAML file in deploy/agones/."""
    out = {}
    for path in sorted(DEPLOY.glob("*.yaml")):
        for doc in yaml.safe_load_all(path.read_text()):
            assert doc["kind"] not in out, f"two {doc['kind']} manifests"
            out[doc["kind"]] = doc
    return out


@pytest.fixture(scope="module")
def schemas() -> dict[tuple[str, str], dict[str, Any]]:
    return {
        **crd_schemas(),
        ("v1", "ConfigMap"): CONFIGMAP_SCHEMA,
        ("v1", "PersistentVolumeClaim"): PVC_SCHEMA,
    }


def test_every_manifest_is_valid_for_its_kind(schemas):
    docs = manifests()
    assert set(docs) == {"Fleet", "FleetAutoscaler", "ConfigMap", "PersistentVolumeClaim"}
    for kind, doc in docs.items():
        assert errors(doc, schemas) == [], kind


@pytest.mark.parametrize(
    ("where", "value", "says"),
    [
        (("spec", "template", "spec", "ports", 0, "portPolicy"), "dynamic", "is not one of"),
        (("spec", "template", "spec", "health", "periodSecond"), 5, "Additional properties"),
        (("spec", "template", "spec", "lists", "rooms", "capacity"), "1", "is not of type"),
        (
            ("spec", "template", "spec", "template", "spec", "containers", 0, "resource"),
            {},
            "Additional properties",
        ),
    ],
)
def test_the_check_catches_a_mistake_in_the_fleet(schemas, where, value, says):
    fleet = copy.deepcopy(manifests()["Fleet"])
    node = fleet
    for key in where[:-1]:
        node = node[key]
    node[where[-1]] = value
    assert any(says in e for e in errors(fleet, schemas))


def test_the_fleet_and_its_autoscaler_agree_with_the_server():
    docs = manifests()
    fleet, fas = docs["Fleet"], docs["FleetAutoscaler"]
    gs = fleet["spec"]["template"]["spec"]
    # the autoscaler scales this fleet on the list the server keeps
    assert fas["spec"]["fleetName"] == fleet["metadata"]["name"]
    assert fas["spec"]["policy"]["list"]["key"] == ROOMS_LIST and ROOMS_LIST in gs["lists"]
    assert USERS_COUNTER in gs["counters"]
    # Agones waits periodSeconds for a ping; the server pings every health_period_s
    assert gs["health"]["periodSeconds"] > AgonesOptions().health_period_s
    pod = gs["template"]["spec"]
    (container,) = [c for c in pod["containers"] if c["name"] == gs["container"]]
    args = build_parser().parse_args(container["args"])
    assert args.command == "server" and args.host == "0.0.0.0"
    assert gs["ports"][0]["containerPort"] == args.port
    assert args.token_file and any(
        args.token_file.startswith(m["mountPath"] + "/") for m in container["volumeMounts"]
    )
    # a CPU request, and no CPU limit (throttling would stall ticks)
    resources = container["resources"]
    assert "cpu" in resources["requests"] and "cpu" not in resources.get("limits", {})
    env = {e["name"]: e["value"] for e in container["env"]}
    assert env["OPENBLAS_NUM_THREADS"] == "1" and env["OMP_NUM_THREADS"] == "1"


@pytest.mark.parametrize(
    ("where", "value", "says"),
    [
        (("data", "rooms toml"), "x = 1", "does not match"),
        (("data", "rooms.toml"), 3, "is not of type"),
        (("immutable",), "yes", "is not of type"),
        (("spec",), {}, "Additional properties"),
    ],
)
def test_the_check_catches_a_mistake_in_the_configmap(schemas, where, value, says):
    cm = copy.deepcopy(manifests()["ConfigMap"])
    node = cm
    for key in where[:-1]:
        node = node[key]
    node[where[-1]] = value
    assert any(says in e for e in errors(cm, schemas))


def _mounted(pod: dict[str, Any], container: dict[str, Any], path: str) -> dict[str, Any]:
    """The pod volume a file path of the container is read from, with ``key``: the file name."""
    for m in container["volumeMounts"]:
        if path.startswith(m["mountPath"].rstrip("/") + "/"):
            (volume,) = [v for v in pod["volumes"] if v["name"] == m["name"]]
            return {**volume, "key": path[len(m["mountPath"].rstrip("/")) + 1 :]}
    raise AssertionError(f"{path} is on no volume of the container")


def test_the_fleets_servers_make_the_rooms_the_lobby_names(tmp_path):
    docs = manifests()
    gs = docs["Fleet"]["spec"]["template"]["spec"]
    pod = gs["template"]["spec"]
    (container,) = [c for c in pod["containers"] if c["name"] == gs["container"]]
    argv = container["args"]
    parser = build_parser()
    args = parser.parse_args(argv)
    # the configuration file is the ConfigMap's key, mounted as a file
    config = _mounted(pod, container, args.config)
    cm = docs["ConfigMap"]
    assert config["configMap"]["name"] == cm["metadata"]["name"]
    text = cm["data"][config["key"]]
    # the room-token secret (the lobby's) and the server-wide tokens are files of the Secret
    for path in (args.token_secret_file, args.token_file, args.metrics_token_file):
        assert "secretName" in _mounted(pod, container, path)["secret"], path
    # the server reads the configuration as `haptic server --config` does (haptic_collab.cli)
    local = tmp_path / config["key"]
    local.write_text(text)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    apply_server_config(sub.choices["server"], local)
    opts = _server_options(parser.parse_args(argv))
    assert opts.token_secret_file == args.token_secret_file
    # a name the lobby allocates is made when its first user arrives, whatever the name
    link = LinkConditions()
    templates = RoomTemplates(opts, opts.room_templates, link, None, None)
    for name in ("anatomy-3", "x", "lab-2026-11-27"):
        assert templates.allows(name), name
    # capacity is one number: the rooms list holds every open room (the default one included)
    # and has a slot per room the server may run; the users counter holds every user of them
    assert gs["lists"][ROOMS_LIST]["capacity"] == opts.max_rooms
    assert not opts.rooms  # no configured room: every room but the default one is a template's
    per_room = [build_room(opts, DEFAULT_ROOM, {}, link, None, None).limits.max_users]
    per_room += [templates.build(f"r{i}").limits.max_users for i in range(1, opts.max_rooms)]
    assert gs["counters"][USERS_COUNTER]["capacity"] == sum(per_room)
    # and what the server checks them against under Agones (it says so where they differ)
    agones = build_agones(opts)
    assert (agones.max_rooms, agones.max_users) == (opts.max_rooms, sum(per_room))


def test_the_fleet_serves_tls_and_keeps_snapshots_on_a_shared_volume():
    docs = manifests()
    gs = docs["Fleet"]["spec"]["template"]["spec"]
    pod = gs["template"]["spec"]
    (container,) = [c for c in pod["containers"] if c["name"] == gs["container"]]
    args = build_parser().parse_args(container["args"])
    # TLS on the game port: the certificate and key are files of a Secret volume
    assert args.tls_cert and args.tls_key
    cert, key = _mounted(pod, container, args.tls_cert), _mounted(pod, container, args.tls_key)
    assert cert["secret"]["secretName"] == key["secret"]["secretName"]
    assert (cert["key"], key["key"]) == ("tls.crt", "tls.key")  # a kubernetes.io/tls Secret
    # the drain's snapshots go to the claim every GameServer mounts, writable by the server
    assert args.snapshot_dir
    mount = next(
        m for m in container["volumeMounts"] if args.snapshot_dir.startswith(m["mountPath"])
    )
    assert not mount.get("readOnly", False)
    volume = _mounted(pod, container, args.snapshot_dir + "/room.npz")
    claim = docs["PersistentVolumeClaim"]
    assert volume["persistentVolumeClaim"]["claimName"] == claim["metadata"]["name"]
    assert claim["spec"]["accessModes"] == ["ReadWriteMany"]  # every GameServer mounts it
    assert pod["securityContext"]["fsGroup"] == pod["securityContext"]["runAsGroup"]
    # the pod lives long enough for the drain to save every room
    assert pod["terminationGracePeriodSeconds"] > args.drain_grace_s


def _dockerfile_instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of the Dockerfile, continuation lines joined."""
    text = (ROOT / "Dockerfile").read_text().replace("\\\n", " ")
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            word, _, rest = line.partition(" ")
            out.append((word.upper(), rest.strip()))
    return out


def test_the_image_runs_the_server_as_a_numeric_non_root_user_with_one_blas_thread():
    steps = _dockerfile_instructions()
    final = steps[max(i for i, (w, _) in enumerate(steps) if w == "FROM") :]
    users = [rest for word, rest in final if word == "USER"]
    assert users, "the final stage sets no USER: it runs as root"
    uid = users[-1].split(":")[0]
    assert uid.isdigit() and int(uid) != 0  # numeric: runAsNonRoot can check it
    fleet_pod = manifests()["Fleet"]["spec"]["template"]["spec"]["template"]["spec"]
    assert fleet_pod["securityContext"]["runAsUser"] == int(uid)
    env = " ".join(rest for word, rest in final if word == "ENV")
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        assert f"{var}=1" in shlex.split(env)
    # the user is made in a RUN before USER switches to it
    made = [i for i, (w, r) in enumerate(final) if w == "RUN" and f"--uid {uid}" in r]
    assert made and made[0] < [w for w, _ in final].index("USER")
