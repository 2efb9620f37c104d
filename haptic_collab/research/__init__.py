"""Research drivers: the paper's figures, the fidelity models and their plots, never imported by
the runtime (server, client, shared).

- :mod:`.multirate`: the paper's 1-D multirate loop simulated in time (Fig. 7-9);
- :mod:`.reproduce`: the data of ``haptic reproduce`` (Fig. 7-9); :mod:`.reproduce_3d` Fig. 10-11
  through the real World and local model;
- :mod:`.fidelity_1d`: the 1-D fidelity model (objects, hands, schemes) of ``haptic bench
  fidelity``; :mod:`.fidelity_3d` its cells through the real World;
- :mod:`.plots`: the figures (matplotlib, the ``plots`` extra).

Free to import the server, the client and shared alike.
"""
