"""The use cases of forestreg, one file each: what every front door (command line, desktop, job
service, batch, plugin hosts, demo) calls.

Each use case takes its inputs (file paths or :class:`~forestreg.engine.core.scan.Scan`\\ s), a
parameter object, a progress callback and a cancel token, and an output folder, and returns a
typed outcome (:class:`~forestreg.app.common.RunOutcome`: ``status``, ``reason``, ``matrix``,
``evidence``, ``timings``; falsy when not ok). Reading the inputs, the final checks (a rigid
matrix, the files' unit) and the transactional writing of the output folder happen here, once.

=====================  ==========================================================
``pair``               one TLS pair from trunk shadows (``forestreg register``)
``plot``               a plot or a saved project of TLS scans (``plot``, ``project run``)
``survey``             every pair of a plot, pose graph and uncertainty (``--pairs``)
``targets``            reflector targets in scans (``targets``)
``comparison``         automatic against target-based registration (``compare``)
``coregistration``     ground-based onto UAV clouds (``coregister``)
``fusion``             co-registered clouds fused (``fuse``)
``trees``              tree detection and measurement (``trees``)
``evaluation``         trees against field records (``evaluate``)
``simulation``         simulated scans and plots with their truth (``simulate``, ``demo``)
``change``             two surveys of one plot compared tree by tree (``change``)
=====================  ==========================================================
"""
