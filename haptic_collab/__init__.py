"""haptic-collab: networked multi-user haptic collaboration on a shared deformable object.

An implementation of Barbagli, Prattichizzo and Salisbury, "A Multirate Approach to Haptic
Interaction with Deformable Objects: Single and Multipoint Contacts" (IJRR 2005).

Everything installs under this one name (nothing else lands at the top of site-packages):

- :mod:`haptic_collab.shared`: the physics and the protocol used by server and client (no I/O);
- :mod:`haptic_collab.server`: the authoritative asyncio server and the global deformable object;
- :mod:`haptic_collab.client`: the 1 kHz local-model servo, devices and the network link;
- :mod:`haptic_collab.cli`: the ``haptic`` command; :mod:`haptic_collab.demo`: ``haptic demo``;
  :mod:`haptic_collab.research.plots`: the figures of ``haptic reproduce`` (matplotlib, the ``plots`` extra);
- ``haptic_collab/web``: the browser viewer (package data, found with :mod:`importlib.resources`).

In the source tree the folders ``server/``, ``client/``, ``shared/`` and ``web/`` stay at the top
level; ``haptic_collab/`` holds symbolic links to them, so the same import names work from a
checkout, an editable install and a wheel.
"""

__version__ = "0.1.0"
