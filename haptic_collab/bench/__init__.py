"""The benchmarks of ``haptic bench``: measurements of the product, never imported by it.

- :mod:`.servo`: the servo loop's timing on this machine (``haptic bench servo``);
- :mod:`.gains`: what a gain update and a cell's design cost the client (``haptic bench gains``);
- :mod:`.world`: the server's simulation tick, the FEM solid's too (``haptic bench server``);
- :mod:`.load`: many clients against one server process (``haptic bench load``; the clients
  in :mod:`.load_clients`);
- :mod:`.fidelity`: the local model against its peers (``haptic bench fidelity``).

Free to import the server, the client and shared alike; neither of those imports this package.
"""
