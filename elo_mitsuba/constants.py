"""One source of truth for every constant of the model.

Units: lengths in millimetres, angles in degrees where the name says ``_deg``, currents in
ampere, transimpedance in V/A. Equation numbers refer to Renner et al. (2023), J. Manuf. Mater.
Process. 7, 87 (CC BY 4.0), "the paper".
"""

# --- Backscatter physics (Sec. 2.1.2-2.1.3) -------------------------------------------------------
#: Saturation value B of Darlington's Eq. 10, eta(theta -> 90 deg) -> B.
DARLINGTON_B = 0.89
#: Coefficients a0..a3 of Reimer's Eq. 11, eta0(Z) = a0 + a1 Z + a2 Z^2 + a3 Z^3.
ETA0_POLYNOMIAL = (-0.0254, 0.016, -1.86e-4, 8.3e-7)
#: Atomic numbers for which Eq. 11 is accepted. The cubic is a fit to measured eta0 of pure
#: elements from carbon to gold (Reimer, Scanning Electron Microscopy, 1998); below Z = 2 it is
#: even negative. We refuse to extrapolate outside [6, 79].
ETA0_Z_RANGE = (6, 79)
#: Lobe width of Eq. 13: k = theta / LOBE_WIDTH_DEG with theta in degrees.
LOBE_WIDTH_DEG = 13.0
#: Acceleration voltage for which Eq. 10 is used here (fitted for 10-100 keV by Darlington).
ACCELERATION_VOLTAGE_KV = 60.0
#: Tolerance on the sum of weight fractions of a composition.
COMPOSITION_SUM_TOL = 1e-6
#: A measured composition (an analysis certificate rounds each element) may miss 1 by this much:
#: it is normalised to sum 1, with a note; beyond it the fractions are refused as a real mismatch.
MEASURED_COMPOSITION_TOL = 1e-3
#: Nominal composition used wherever the paper says Ti-6Al-4V (docs/paper-notes.md §5).
DEFAULT_MATERIAL = "Ti-6Al-4V"

# --- Measurement chain (Eq. 3, Eq. 9, Sec. 2.4) -----------------------------------------------------
BEAM_CURRENT_A = 3e-3
TRANSIMPEDANCE_V_PER_A = 1e5
ELEMENTARY_CHARGE_C = 1.602176634e-19

# --- Sampling ---------------------------------------------------------------------------------------
#: Largest seed (renders, sweeps, the optimiser): Mitsuba's samplers and numpy's take 32-bit seeds.
MAX_SEED = (1 << 32) - 1
#: Largest samples per pixel: Mitsuba's samplers count them in 32 bits (a sweep's spp = 1e300 was
#: carried to the time estimate and printed as a 301-digit number).
MAX_SPP = (1 << 32) - 1

# --- ATHENE validation geometry (Sec. 2.2) ----------------------------------------------------------
DETECTOR_HEIGHT_MM = 272.0        # d_h
DETECTOR_DISTANCE_MM = 127.0      # d_w, from the z-axis
DETECTOR_DIAMETER_MM = 50.0       # copper discs
FIELD_MM = 80.0                   # scan field width
#: Work distance w_d (gun pivot height above the build plane). The paper does not give ATHENE's;
#: we choose 400 mm: above the detectors (272 mm) and typical of PBF-EB guns, giving a deflection
#: angle of 8.0 deg at the corner of the 80 mm field. It is a scene parameter everywhere.
WORK_DISTANCE_MM = 400.0

#: Detector channel names and the unit vector from the z-axis towards each (Eq. 17).
DETECTOR_DIRECTIONS = {
    "right": (1.0, 0.0),
    "left": (-1.0, 0.0),
    "back": (0.0, 1.0),
    "front": (0.0, -1.0),
}
DETECTOR_NAMES = tuple(DETECTOR_DIRECTIONS)

#: Table 1: detector layouts by inclination zeta (deg) -> (d_h, d_w) in mm.
TABLE1_LAYOUTS = {
    25: (272.0, 127.0),
    50: (192.7, 229.6),
    60: (149.9, 259.6),
    75: (77.6, 289.6),
}

# --- Signal chain noise (issue 27, the design metric) -----------------------------------------------
#: Dwell time of the beam on one pixel (s). Our choice: the paper gives none; ELO scans of PBF-EB
#: machines dwell ~0.1-1 us per point. With BEAM_CURRENT_A it sets the primary electrons per pixel.
PIXEL_DWELL_S = 1e-6
#: RMS noise of the transimpedance amplifier's output over one pixel (V). Our choice (1 mV at
#: 1e5 V/A: 10 nA input-referred), a parameter of the metric everywhere.
AMPLIFIER_NOISE_V = 1e-3

# --- ATHENE-like chamber (scenes_xml/parts/chamber.xml; scenes_xml/athene_flat.xml documents it) ----
#: Interior: x, y, z ranges (mm). tests/test_design.py checks these against parts/chamber.xml.
CHAMBER_INTERIOR_MM = ((-350.0, 350.0), (-450.0, 330.0), (0.0, 550.0))
#: Half-width of the square gun-column opening in the ceiling (|x|, |y| < 50 mm): the column runs
#: from the ceiling down to the beam pivot at the work distance.
COLUMN_HALF_WIDTH_MM = 50.0
#: Radiation-protection sheet hanging from the ceiling: its y range and lower edge z (mm), full width.
SHEET_Y_MM = (200.0, 202.0)
SHEET_BOTTOM_MM = 320.0

# --- Software environment --------------------------------------------------------------------------
#: Oldest LLVM that Mitsuba's llvm variants run with here (Debian's 15/16 abort on fminimum).
MIN_LLVM_MAJOR = 17
DEFAULT_VARIANT = "llvm_ad_mono"
VARIANT_ENV_VAR = "ELO_MITSUBA_VARIANT"
SUPPORTED_VARIANTS = ("llvm_ad_mono", "cuda_ad_mono")
