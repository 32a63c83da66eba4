"""Validation of elo-mitsuba against Renner et al. 2023 (J. Manuf. Mater. Process. 7, 87).

One command regenerates every claim of the paper that a simulation can check, as figures in the
style of the paper's and a report that puts the paper's number beside ours:

    python -m validation            # default settings, ~4-7 min on 2 cores -> ./validation-report/REPORT.md
    python -m validation --quick    # tiny resolutions, ~40 s -> ./validation-quick/REPORT.md
    python -m validation --update-report   # rewrites the committed validation/REPORT.md
    elo-mitsuba validate [--quick]  # the same, from a source checkout

Studies (one module each, run in this order):

========================  =======================================================================
``checks``                energy (hemisphere integral of g_BSE = eta), four-detector symmetry,
                          misprints (Eqs. 14, A1) and the paper's arithmetic
``stsa``                  Fig. 4: STSA contrast of a flat plate in the ATHENE-like chamber
``corrugated``            Fig. 10: M_x, Eq. 26 and Eq. 24 on the corrugated sheet
``reflectance``           Figs. 12-13: reflectance maps with masking
``masking``               Table 1, Figs. 14-15: masking and contrast on the melt plate
``melt_plate``            Figs. 6, 7, 11 (+ Fig. 3b): M_x, Eq. 26, beam blur, height reconstruction
``convergence``           Sec. 2.1.1 / App. A: error against a converged reference vs spp, events,
                          detector samples; the settings for 1 % and 0.1 %
``topography``            beyond the paper: model-based gradient vs Eq. 26 on the sawtooth plate,
                          noise, blur, 2nd event, detector calibration
``inversion``             beyond the paper: heights by inverting the forward model vs the model
                          gradient + integration (melt plate, steep hills, masking, chamber)
``design``                beyond the paper: the Cramer-Rao bound of the gradient (the design metric)
                          against model-gradient fits on renders; Table 1 under it
``defects``               beyond the paper: heights at pores, bumps and steps; the calibration of
                          height_error and dzdx_sigma on four surfaces
========================  =======================================================================

The package lives only in a source checkout (it is not installed with elo_mitsuba). Importing it
is cheap; Mitsuba is loaded when a study runs.
"""

from __future__ import annotations

from .report import VERDICTS, Row, StudyResult  # noqa: F401

#: Study names in the order they run (module validation.study_<name>).
STUDIES = ("checks", "stsa", "corrugated", "reflectance", "masking", "melt_plate", "convergence", "topography",
           "inversion", "design", "defects")


def run(quick: bool = False, output_dir=None, only=None, log=print, json_path=None, figures=True):
    """Run the studies and write ``REPORT.md`` (and ``figures/``) into ``output_dir``.

    Parameters
    ----------
    quick : bool
        Tiny resolutions and sample counts (about a minute); the default settings take about
        ten minutes on two cores.
    output_dir : path, optional
        Default, in the current folder: ``validation-report/``, ``validation-quick/`` for
        ``quick``, ``validation-partial/`` with ``only`` (the committed ``validation/`` only when
        given explicitly, as ``--update-report`` does).
    only : iterable of str, optional
        Subset of :data:`STUDIES`.
    log : callable or None
        Progress messages (``print`` by default).
    json_path : path, optional
        Also write the rows (with their key numbers) as JSON there.
    figures : bool
        Draw the figures (False: numbers only).

    Returns
    -------
    validation.runner.Validation
        ``.rows`` (list of :class:`Row`), ``.studies``, ``.report_path``.
    """
    from .runner import run_validation

    return run_validation(quick=quick, output_dir=output_dir, only=only, log=log,
                          json_path=json_path, figures=figures)
