"""Survey: every pair of a plot's scans (or those whose scanners stand close), a pose graph
weighted by each pair's evidence, inconsistent links dropped, and each pose's uncertainty
(``forestreg plot --pairs``, ``project run --pairs``).

The run itself (reading, writing the plot folder) is :func:`forestreg.app.plot.run_plot`; this
file holds the survey's inputs: checked before any work and put into the project.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional, Sequence


def check_survey_options(
    pairs: Optional[str] = None, positions: Optional[str] = None, prior_poses: Optional[str] = None
) -> None:
    """Bad ``pairs`` ("all", "within:D", "centre"), positions CSV or prior poses file: one line
    (exit 2), before any work."""
    from ..engine.tls.survey import parse_pairs, read_positions_csv, read_prior_poses

    if pairs:
        parse_pairs(pairs)
    if positions:
        read_positions_csv(positions)
    if prior_poses:
        read_prior_poses(prior_poses)


def survey_inputs(
    project,
    known: Callable[[str, str], str],
    *,
    positions: Optional[str] = None,
    prior_poses: Optional[str] = None,
    fixed: Sequence[str] = (),
) -> None:
    """Scanner positions (CSV scan,x,y,z), prior poses and the names of fixed scans into the
    project; ``known(name, option)`` resolves a scan name or refuses it."""
    from ..engine.tls.survey import read_positions_csv, read_prior_poses

    if positions:
        for name, xyz in read_positions_csv(positions).items():
            project.scan(known(name, "--positions")).scanner_position = xyz
    if prior_poses:
        for name, pose in read_prior_poses(prior_poses).items():
            project.scan(known(name, "--prior-poses")).prior_pose = pose
    for name in ",".join(fixed or []).split(","):
        if name.strip():
            known(name.strip(), "--fixed")


def fixed_names(project, fixed: Sequence[str] = ()) -> tuple[str, ...]:
    """The scans named in ``fixed`` (comma-separated items, by scan name or file name)."""
    names = {s.name: s.name for s in project.scans} | {Path(s.path).name: s.name for s in project.scans}
    return tuple(names.get(n.strip(), n.strip()) for n in ",".join(fixed or []).split(",") if n.strip())


def survey_params(pairs: str, project, fixed: Sequence[str] = (), base=None):
    """The :class:`~forestreg.engine.tls.params.SurveyParams` of ``pairs`` ("all", "within:D",
    "centre") with the fixed scans, the other settings from ``base`` (default the defaults)."""
    from ..engine.tls.params import SurveyParams
    from ..engine.tls.survey import parse_pairs

    which, distance = parse_pairs(pairs)
    base = base or SurveyParams()
    return base.replace(
        pairs=which,
        max_distance_m=distance if which == "within" else base.max_distance_m,
        fixed=fixed_names(project, fixed),
    )


def register_survey(
    project,
    pairs: str,
    *,
    fixed: Sequence[str] = (),
    rerun: bool = False,
    scans=None,
    progress=None,
    cancel=None,
    base=None,
    on_link_done=None,
):
    """Register every pair the survey asks for, solve the pose graph and record the uncertainty
    in the project (``base``: the other :class:`~forestreg.engine.tls.params.SurveyParams`;
    ``on_link_done(project)`` after each finished link, e.g. saving it); returns the engine's
    :class:`~forestreg.engine.tls.plot.PlotOutcome`."""
    from ..engine.tls.survey import register_survey as run
    from .common import with_cancel

    return run(
        project,
        survey_params(pairs, project, fixed, base),
        rerun=rerun,
        progress=with_cancel(progress, cancel),
        scans=scans,
        on_link_done=on_link_done,
    )
