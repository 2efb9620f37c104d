"""Client sessions as the tests meet them: an object a welcome describes, a session that received
its welcome, and contact patches on the object's top plane."""

from __future__ import annotations

from typing import Any

from haptic_collab.client.session import ClientSession
from haptic_collab.shared.protocol import (
    DeviceInfo,
    ObjectInfo,
    Patch,
    PlaneModel,
    RecommendedGains,
    Welcome,
    encode,
)

#: The object a welcome describes: an octahedron of radius 0.1 m about the origin [m].
WELCOME_OBJECT = ObjectInfo(
    n_vertices=6,
    n_faces=8,
    center_m=(0, 0, 0),
    radius_m=0.1,
    bounds_min_m=(-0.1, -0.1, -0.1),
    bounds_max_m=(0.1, 0.1, 0.1),
    top_m=(0, 0, 0.1),
    top_normal=(0, 0, 1),
    side_m=(0.1, 0, 0),
    side_normal=(1, 0, 0),
)


def plane_patch(
    tick: int, k_o: float, k_o_eff: float | None = None, k_o_stiff: float | None = None
) -> str:
    """A ``patch`` frame: 2 mm into the top plane z = 0.1 m of :data:`WELCOME_OBJECT`, in contact.

    ``k_o``, ``k_o_eff`` (default ``k_o``) and ``k_o_stiff`` (default None: an uncoupled contact)
    are the patch's stiffnesses [N/m]; ``b_o`` is 0.
    """
    return encode(
        Patch(
            tick=tick,
            primitive=PlaneModel(point=(0, 0, 0.1), normal=(0, 0, 1)),
            proxy_m=(0, 0, 0.1),
            normal=(0, 0, 1),
            penetration_m=0.002,
            in_contact=True,
            k_o=k_o,
            k_o_eff=k_o if k_o_eff is None else k_o_eff,
            k_o_stiff=k_o_stiff,
            b_o=0.0,
        )
    )


def welcomed_session(
    name: str, user_id: str, max_stiffness_n_per_m: float = 1000.0, **options: Any
) -> ClientSession:
    """A :class:`ClientSession` named ``name`` that received its welcome (as ``user_id``) at 0 s.

    The device states ``max_stiffness_n_per_m`` [N/m]; the welcome a 20 Hz simulation of
    :data:`WELCOME_OBJECT`. ``options`` are the session's other keyword arguments.
    """
    s = ClientSession(
        name, device=DeviceInfo(max_stiffness_n_per_m=max_stiffness_n_per_m), **options
    )
    s.receive(
        encode(
            Welcome(
                user_id=user_id, name=name, role="user", sim_rate_hz=20.0, object=WELCOME_OBJECT
            )
        ),
        0.0,
    )
    return s


def session_patch(tick: int, k_o_eff: float = 300.0, k_o: float = 320.0) -> str:
    """A contact patch on the top plane of :data:`WELCOME_OBJECT` (the session tests' default
    stiffnesses, K_o 320 N/m and K_o,eff 300 N/m)."""
    return plane_patch(tick, k_o, k_o_eff)


def press_patch(
    tick: int,
    force_n: float,
    k_true: float,
    *,
    k_o: float,
    b_o: float = 0.0,
    gains: RecommendedGains | None = None,
    rest_plane: PlaneModel | None = None,
    in_contact: bool = True,
) -> str:
    """A patch of a press on the top plane z = 0.1 m of :data:`WELCOME_OBJECT`, a spring of
    ``k_true`` [N/m] reported at ``k_o``: the surface pushed in by the force ``force_n`` [N] the
    simulation applied from this user, with ``b_o``, ``gains`` and ``rest_plane`` as given;
    out of contact (``in_contact`` False) the probe 10 mm outside."""
    z = 0.1 - force_n / k_true
    return encode(
        Patch(
            tick=tick,
            primitive=PlaneModel(point=(0, 0, z), normal=(0, 0, 1)),
            proxy_m=(0, 0, z),
            normal=(0, 0, 1),
            penetration_m=0.001 if in_contact else -0.01,
            in_contact=in_contact,
            k_o=k_o,
            k_o_eff=k_o,
            b_o=b_o,
            own_force_n=force_n,
            gains=gains,
            rest_plane=rest_plane,
        )
    )
