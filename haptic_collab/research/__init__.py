"""Research drivers: the paper's figures, the fidelity models and their plots, never imported by
the runtime (server, client, shared).

- :mod:`.multirate`: the paper's 1-D multirate loop simulated in time (Fig. 7-9);
- :mod:`.reproduce`: the data of ``haptic reproduce`` (Fig. 7-9); :mod:`.reproduce_3d` Fig. 10-11
  through the real World and local model: :mod:`.press_3d` one press of the stiffened balloon and
  its judgement, :mod:`.plots_3d` their drawings;
- :mod:`.harness_3d`: the 3-D harness both World drivers share (the World of an object, the
  simulated device and hand, the product's servo, the multirate loop);
- :mod:`.fidelity_1d`: the 1-D fidelity model's vectorised simulator of ``haptic bench
  fidelity``, with :mod:`.fidelity_cases` (objects, trajectories, cells), :mod:`.fidelity_schemes`
  (the schemes and their tunings) and :mod:`.fidelity_metrics` (what a user would notice);
  :mod:`.fidelity_3d` its cells through the real World, each scheme's user built by
  :mod:`.fidelity_users_3d`, two users by :mod:`.fidelity_pairs_3d`;
- :mod:`.plots`: the figures (matplotlib, the ``plots`` extra).

Free to import the server, the client and shared alike.
"""
