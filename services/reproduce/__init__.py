"""``archer reproduce``: the thesis's ARCHER figures and tables, regenerated on this machine.

An offline tool, not the robot's code: it runs lockstep campaigns on the twin, benches and the
examples, draws each figure with the thesis's axes and quantities, and writes a report that puts
the thesis's number (with its line in the thesis) beside ours and says whether it reproduced.

- :mod:`.engine`: one lockstep run with what the figures need (trace, phases, impacts), campaigns of
  them on the campaigns' pool (resumable, one JSON line per run), the shared run context;
- :mod:`.items`: what an item is and its result (rows, figures, verdict); :mod:`.catalogue`: all of them;
- :mod:`.hopping`, :mod:`.planning`, :mod:`.timing`: the items themselves; :mod:`.figures`: drawing helpers;
- :mod:`.report`: ``report.md`` from the items' results.
"""
