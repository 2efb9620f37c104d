"""The gain policy: which local-model gains render for a patch, and why, in one place.

Pure like the rest of :mod:`shared` (time is passed in). The modules, in the order a patch meets
them:

- :mod:`.policy`: the policy's own constants and the loop delay it designs for (the round trips'
  percentile, held through a contact);
- :mod:`.key`: the gain key, what a design depends on besides K_o;
- :mod:`.table`: designs on a geometric grid of K_o; :mod:`.table_file`: the tables on disk,
  the shipped ones (:mod:`.tables`) and the design code's hash they hold for;
- :mod:`.design`: a cell's design with the hand in the loop; :mod:`.search`: its candidates;
  :mod:`.coupled_design`: users coupled through the object;
- :mod:`.interim`: the check any gains pass before they render for a cell without a design;
- :mod:`.own_response`, :mod:`.verified_plane`, :mod:`.rest_plane`: the planes a user alone on
  the object may render;
- :mod:`.choose`: the choice itself, :func:`.choose.choose`, which the client session asks for
  every patch.
"""
