"""forestreg.ui: the PySide6 + pyvista desktop GUI over the engine's project model.

Nothing here may be imported by the engine; the engine never imports Qt. Modules:

* :mod:`.app` -- ``forestreg gui`` / ``python -m forestreg.ui.app``: the window, or a scripted
  run without a display (``--offscreen --project P --run --screenshot OUT.png``);
* :mod:`.main_window` -- the main window (menus, toolbar, docks, running and exporting);
* :mod:`.project_model` -- the project tree (Qt item model over ``engine.project.Project``);
* :mod:`.worker`, :mod:`.tasks` -- engine calls in QThreads with progress and cancelling;
* :mod:`.scene_data`, :mod:`.scene_view` -- the decimated 3D view (pyvistaqt, or off-screen images);
* :mod:`.top_view` -- the 2D top view of slices, VOPs and matches, with the survey quality
  (pose uncertainty at each scanner, dropped links) (matplotlib);
* :mod:`.manual_mode`, :mod:`.manual_panel`, :mod:`.tie_points` -- targets, manual registration,
  the reference and moving scans side by side for picking tie points;
* :mod:`.params_panel`, :mod:`.results_tables`, :mod:`.log_pane` -- the other panels;
* :mod:`.sample` -- the simulated sample plot behind "Open sample plot".
"""
