"""Playing a built model: exporters, the breathing schedule, tracked points, the viewer server, the demo.

Owns: :mod:`~lungdeform.playback.schedule` (the volume over time an export plays: a curve CSV, a
simulated preset, a plain cycle), :mod:`~lungdeform.playback.export` (glTF 2.0 with morph targets,
ParaView series), :mod:`~lungdeform.playback.usd` (OpenUSD / USDZ: one blend shape per lung, or baked points;
usd-core, the optional extra ``usd``), :mod:`~lungdeform.playback.markers` (markers carried in a glb),
:mod:`~lungdeform.playback.trajectory` (where interior points go as the model breathes),
:mod:`~lungdeform.playback.displacement_field` (the motion as a displacement-field image on a reference grid, docs/RADIOTHERAPY.md;
its per-voxel numba passes in :mod:`~lungdeform.playback.voxel`),
:mod:`~lungdeform.playback.structures` (RTSTRUCT structures moved per breathing state, their ITV and motion table),
:mod:`~lungdeform.playback.density` (mass-conserving CT numbers, MIP/AIP/MinIP over phases),
:mod:`~lungdeform.playback.rigid` (a structure kept rigid inside a field),
:mod:`~lungdeform.playback.server` (the three.js viewer on 127.0.0.1), :mod:`~lungdeform.playback.tracefeed` (a recorded trace
with its measured and predicted volume and, with a prediction, its beam gate, as the viewer plays it) and :mod:`~lungdeform.playback.demo`
(the demo run; its off-screen snapshot is drawn by :mod:`lungdeform.plot`).

May import: :mod:`lungdeform.data`, :mod:`lungdeform.io`, :mod:`lungdeform.breathing`,
:mod:`lungdeform.model`, :mod:`lungdeform.interior`, :mod:`lungdeform.geometry` and the core modules;
never the fitting code.
"""
