"""Every tuning constant of the gain policy, in one place, each with its source or measurement.

What renders for a patch is decided by :func:`shared.gains.choose.choose`, from designs
(:mod:`shared.gains.design`), checks (:mod:`shared.gains.interim`) and planes
(:mod:`shared.gains.verified_plane`, :mod:`shared.gains.rest_plane`); every number those rules
were tuned with is here, grouped by the module that uses it (which imports it by name). The
constants the design reads are part of the design code the shipped gain tables hold for
(:func:`shared.gains.table_file.design_code_hash` hashes those, and only those, of this module):
changing one asks for the tables to be built again (``haptic gains-table --ship``;
``tools/codegen --check`` says so); changing one only the choice reads does not. Measurements and their dates are in docs/results/; the constants of the physics (the
hand box, :mod:`shared.full_loop`) and of the numerics stay with their code.
"""

from __future__ import annotations

import math

# ------------------------------------------------------------------
# The loop delay and what renders while a check runs (shared.gains.delay, shared.gains.choose)

#: Round trips over which the loop delay is measured (pings every 0.5 s: 10 s).
RTT_WINDOW = 20

#: Percentile of those round trips the delay is measured at: conservative under steady jitter,
#: yet one stall does not raise it.
RTT_PERCENTILE = 90.0

#: A lower loop delay is designed for only after it has been measured for this long [s], and
#: only out of contact (:class:`shared.gains.delay.DelayHold`).
DELAY_FALL_S = 5.0

#: K_h / K_o_eff of the unverified fallback a contact renders while the check for its new
#: coupling class or larger delay runs (:func:`shared.gains.choose.choose`): a proportional
#: model, no own-force compensation, the device's whole damper, zero-order hold. Measured with
#: the hand in the loop (every hand of the box, every sampling tick, the Phantom Desktop's
#: 10 N*s/m): spectral radius at most 0.988 at K_h / K_o of 0.1, 0.15 and 0.25, K_o 30, 100,
#: 300, 600, 1000, 2000 and 4000 N/m and 0, 1, 2, 4 and 8 ticks of delay (K_h capped at the
#: device's 1 kN/m), where half K_o_eff, used before, reached 1.10 at 300 N/m and 1.40 at
#: 1000 N/m (tests/client/test_first_contact.py checks part of that grid). It is felt about a
#: fifth as stiff as the object; a compensated fallback (C_h = 1/K_h, felt as the object in a
#: held press) is not stable without its own check: at K_h / K_o of 0.1 and 0.25 it passed the
#: design's test in 5 of 75 cases at 20 Hz (K_o 30-3000 N/m, 0-8 ticks, coupling classes 1-4),
#: spectral radius up to 1.42 with a tick or more of delay (2026-11-27). A grid, not a proof;
#: not established for a device without a damper.
FALLBACK_K_RATIO = 0.25

#: Largest ratio of static felt stiffness a contact's rendering may step by when a design
#: arrives while checked interim gains render (:func:`shared.gains.choose.choose` keeps those
#: until the contact ends): a stiffness JND of 10 % (Jones and Hunter 1990; docs/fidelity.md).
#: On a busy 2-core machine a FEM solid's design arrived seconds into a press at 6 ticks of
#: delay and the hand felt 47 then 235 N/m (docs/results/gain-policy-choose-2026-11-27.json).
HOLD_FELT_STEP = 1.1

#: Distance [m] the proxy may slide along the surface before the own-response check starts over
#: (:meth:`client.session.ClientSession._object_as_reported`): on a 5 cm radius, 0.5 mm of slide
#: deepens the measured surface by 2.5 um, under a hundredth of what a 0.3 N spread shows on
#: 1000 N/m.
OWN_RESPONSE_SLIDE_M = 0.5e-3

#: Cells of the gain table below a lone contact's own that its coupled class is checked for ahead
#: of need (:func:`shared.gains.choose.likely_next`): a second user's press lowered K_o_eff by 12 % in the
#: demo, two cells of 10 %.
COUPLED_CELLS_BELOW = 2

#: Distance [m] from the surface within which another user's probe has the server check, ahead
#: of need, the coupled pair it would make with a resting user (:mod:`shared.gains.group`,
#: :meth:`server.gains.GainAdvisor.hold_pairs`): a check takes 1-3 s of the design worker
#: (12-24 coupled loops of about 0.1 s), and the stress demo's pressing hand comes down at
#: about 5 cm/s from 3 cm above the surface (docs/real-objects.md). 5 cm: over a second ahead
#: at that speed, and the demo's start position is inside it.
PAIR_LOOKAHEAD_M = 0.05

#: Pair checks waiting at most; the newest run first and the oldest are dropped (a hand moving
#: over the object asks for one bucket after another, and the one it is over matters most).
#: Each verified bucket asks for its three neighbours (the partner's cell either side, the next
#: coupling class), so 8 hold a bucket's and a few more.
PAIR_QUEUE = 8

# ------------------------------------------------------------------
# The stability margin all gains are held to (shared.stability_margin)

#: Slowest accepted decay of any *oscillating* mode of the full loop [1/s]: its eigenvalue over
#: one simulation period must have magnitude at most exp(-MIN_DECAY_RATE * N * T). 1/s: a
#: vibration falls to a third within a second; the box's least damped hand (0.6 kg, 2 N*s/m) alone
#: decays at 1.7/s.
MIN_DECAY_RATE_PER_S = 1.0

#: Modes slower than this [Hz] are creep, not vibration (the integral slowly pushing a stiff hand
#: out): they need only be stable (|eigenvalue| < 1), not decay at MIN_DECAY_RATE_PER_S.
CREEP_FREQUENCY_HZ = 0.5

#: Largest ratio between neighbouring K_o points a design is checked at (:func:`shared.stability_margin.k_o_points`).
K_O_CHECK_RATIO = 4.0


# ------------------------------------------------------------------
# The band of hand motion transparency is judged over (shared.felt_stiffness)

#: Frequencies [Hz] the transparency of a design with own-force compensation is judged at: the
#: band of voluntary hand motion in which people judge stiffness by pressing (0.5-8 Hz; the
#: fidelity benchmark ranks over the same band, docs/fidelity.md). At 1 Hz alone a 10 N*s/m damper
#: at 1000 N/m passed as 1.00 K_o while a hand felt it as 1.12-1.22 K_o at 8 Hz.
FELT_BAND_HZ: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0, 8.0)


# ------------------------------------------------------------------
# The gain key: the K_o grid, the design's K_o range, the coupling classes (shared.gains.key)

#: Ratio classes above this are designed as rigid (:func:`shared.gains.key.stiff_ratio_class`).
MAX_STIFF_RATIO_CLASS = 256.0

#: Every class :func:`shared.gains.key.stiff_ratio_class` returns, ascending: 1, sqrt(2), 2, 2 sqrt(2), 4, then
#: the powers of 2 up to :data:`MAX_STIFF_RATIO_CLASS`, then ``inf``.
STIFF_RATIO_CLASSES: tuple[float, ...] = (
    1.0,
    *(2.0 ** (k / 2.0) for k in range(1, 5)),
    *(2.0**k for k in range(3, int(math.log2(MAX_STIFF_RATIO_CLASS)) + 1)),
    math.inf,
)

#: :attr:`shared.gains.key.GainKey.stiffer_by`'s default: the product's designs hold on an object up to this
#: fraction stiffer than the K_o reported (docs/fidelity.md: objects the design did not see).
STIFFER_BY = 0.25

#: The product's design margin: its clients' designs hold on an object this fraction softer than
#: the bottom of the cell (the paper's advice to design for a lower K_o than reported;
#: ``ClientSession.margin``, ``GainAdvisor.margin``).
DESIGN_MARGIN = 0.15

#: Steps of :data:`DESIGN_TIE` a design may give up to be checked down to the softer object of the
#: model error, ``K_o / (1 + stiffer_by)`` (:func:`shared.gains.design.softest_k_o`), instead of
#: the margin's ``(1 - margin) K_o``: one step, so that the wider check costs less than a stiffness
#: JND (two steps). Checked only to 0.85 K_o, a design for 100 N/m at 10 Hz with one tick of delay
#: held the box's loose heavy hand in a ring decaying at 0.69/s on a spring 20 % softer than
#: reported (spectral radius 0.933 against the margin's 0.905), which a second user's release
#: set off; checked to 0.80 K_o everywhere, the cells of 1000 N/m with 10 ticks of delay lost
#: their compensated designs (the paper's P, a fifth as stiff) and a press on a stiffening
#: object cycled between them and the compensated verified planes (docs/fidelity.md).
SOFT_END_COST_STEPS = 1

#: Ratio between neighbouring K_o grid points of a :class:`shared.gains.table.GainTable`.
K_O_GRID_RATIO = 1.1

#: Object dampings B_o [N/m] (eq. 9) a shipped design for B_o = 0 is checked at, offline, to be
#: rendered for a key with B_o > 0 (:func:`shared.gains.damping_cover.covered_b_o`; ``b_o_covered``
#: in a shipped table). Whole N/m, as the key quantizes B_o (:func:`shared.gains.key.make_gain_key`),
#: doubling from 1 to 64: the default liver sphere reports 7.7 N/m at its top and 53 at its side
#: (docs/fem.md). Doubling, not a finer ratio, for the cost: a check is 0.1-0.4 s of CPU and the
#: two profiles hold 1363 distinct designs (docs/results/fem-table-cover-2026-11-27.json).
B_O_COVER_LATTICE: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0)

#: The coupling class in use falls only when the measured one is this many times lower.
STIFF_CLASS_FALL = 4.0


# ------------------------------------------------------------------
# The design's candidates and ranking (shared.gains.search)

#: C_h K_h values the design tries with own-force compensation (:mod:`shared.gains.design`). At 1
#: the local model is ``F = K_h (x - x_o) + F_s``: in a held press the probe settles on the surface
#: with ``F = K_o x``, the object's own stiffness whatever K_h and whatever the error in K_o (the
#: simulation loop's static gain ``1 - K_h / K_o`` must stay inside (-1, 1)); for coupled users
#: the held press is the object's own physics, the others' pushes included. Ratios below 1 feel
#: softer in a held press; they won only at K_o above the device's stiffness, where the paper's PI
#: does as well, and made a contact's rendering change with its coupling class (a user resting
#: with 0.42 N felt 0.40 N while another pressed), so they are not tried. The one exception is
#: the plane above the device's stiffness (C_h = 1 / K_o with K_h capped below K_o,
#: :func:`shared.gains.design.design_gains`): there no ratio of 1 can be rendered.
OWN_FORCE_RATIOS: tuple[float, ...] = (1.0,)

#: Step [ln of the felt stiffness ratio] in which a design's error on the design model is
#: compared (:func:`shared.gains.design.design_gains`): half the fidelity benchmark's tie, ln(1.1)
#: (a stiffness JND of 10 %, docs/fidelity.md). Within a step, the design more transparent on an
#: object stiffer or softer than reported (:attr:`shared.gains.key.GainKey.stiffer_by`) wins.
DESIGN_TIE = 0.5 * math.log(1.1)


# ------------------------------------------------------------------
# Interim gains: the generic rungs checked while a cell's design runs (shared.gains.interim)

#: Generic interim gains tried when no known gains pass, in order: (K_h, I) as multiples of the
#: cell's lowest K_o, lo = (1 - margin) g_i [N/m], i.e. K_h = a lo [N/m] and I = b lo [N/(m*s)],
#: with the device's full damper B_h and a zero-order hold. The PI one only with a damper and a
#: PI key: with a 10 N*s/m damper at 1 kHz / 20 Hz it passed at K_o = 30 to 3000 N/m and 0 to 3
#: ticks of delay, and no integral passed without a damper; P with K_h = 0.1 lo passed everywhere
#: but at 3000 N/m with a delay, hence 0.05.
INTERIM_LADDER: tuple[tuple[float, float], ...] = ((0.2, 2.0), (0.2, 0.0), (0.1, 0.0), (0.05, 0.0))

#: Generic interim gains with own-force compensation, tried first where the key allows it: K_h =
#: a lo (at most the device's), C_h = 1 / K_h, the device's full damper, zero-order hold and, with
#: a damper, first-order hold. They feel the object's own stiffness in a held press
#: (:mod:`shared.gains.design`), so a user whose contact becomes coupled to another's keeps
#: feeling it while the coupled design runs. For a coupled contact (class 2 and 4, 20 Hz, 0 and 2
#: ticks, 100-1000 N/m, the Phantom Desktop's 10 N*s/m) the zero-order rungs passed in 1 of 12
#: cases, with first-order ones 8; without a damper no compensated gains passed there, so the
#: first-order rungs are not tried; nor below :data:`INTERIM_OWN_FORCE_FOH` lo (a coupled
#: contact's loop gain 1 - K_h / K_o' nears 1 as K_h falls, and a failed check delays the interim
#: gains).
INTERIM_OWN_FORCE: tuple[float, ...] = (1.0, 0.5, 0.25, 0.1, 0.05)

#: The least rung of :data:`INTERIM_OWN_FORCE` tried with first-order hold (see there).
INTERIM_OWN_FORCE_FOH = 0.5


# ------------------------------------------------------------------
# The verified plane (shared.gains.verified_plane)

#: How far the object may be off the K_o reported for the verified plane: it is checked from this
#: fraction softer than the bottom of its cell to this fraction stiffer than its top (the own-response
#: check verifies to :data:`shared.gains.policy.TOLERANCE`, inside it).
VERIFIED_RANGE = 0.05

#: The capped plane is tried in cells up to this factor above the device's stiffness: its felt
#: error at the grid point, ln(g / K_h) <= 0.22 (up to about 0.3 at the top of the cell), is of
#: the order of what the cell's design gives up to its damper and a K_h below the device's (at
#: 1200 N/m on the benchmark's device, 1000 N/m and 10 N*s/m, 20 conditions: the capped plane
#: 0.145 at its grid point against the design's 0.08-0.27). Further up every rendering is held
#: to the device's stiffness, the designs are capped planes already (K_h the device's, C_h =
#: 1 / K_o) and their damper is felt little: at 3000 N/m the capped plane was closer at its grid
#: point in none of 20 conditions (1.098 against 0.96-1.098), so the client does not spend the
#: check.
CAPPED_PLANE_MAX = 1.25

#: The capped plane's compensation steps c: ``C_h = (1 - c) / g + c / K_max`` (:mod:`shared.gains.verified_plane`),
#: from the object's compliance at the cell's grid point (c = 0: the plane stays at the rest
#: surface, felt as the device's stiffness) to the device's (c = 1: the object's own stiffness
#: felt statically, through the simulation loop).
CAPPED_COMPENSATION: tuple[float, ...] = (0.0, 0.25, 0.5, 0.75, 1.0)

#: Probe dampers the plane is tried with, lightest first, as fractions of the device's B_h limit
#: (0 to 5 N*s/m on the benchmark's 10 N*s/m device; 0 to 2.5 on a 5 N*s/m one).
PLANE_DAMPERS: tuple[float, ...] = (0.0, 0.025, 0.05, 0.1, 0.15, 0.25, 0.35, 0.5)

#: The cells whose planes a client checks ahead, in the background, around the cell of the K_o
#: its patches report: from this factor of that K_o ...
AHEAD_SOFTER = 0.5

#: ... to this factor of it (up to :data:`CAPPED_PLANE_MAX` times the device's stiffness). A press
#: into an exponentially stiffening object (Fung 1993) 10 mm deep reports 2.7 times its K_o at
#: rest (docs/fidelity.md); a spring reported 20 % off is identified within one to three cells.
AHEAD_STIFFER = 3.0

#: A stiffness JND of 10 % (docs/fidelity.md) as a felt error [ln]: a difference a hand can feel.
DESIGN_OVER_REST = math.log(1.1)


# ------------------------------------------------------------------
# The rest plane (shared.gains.rest_plane)

#: After a verified plane has rendered in a contact, the rest plane renders again only once none
#: has for this long [s] (the patches' ticks). A press that crossed from the rest plane to the
#: verified planes of a stiffening object and back every cycle rang (7 Hz, 8 mm peak to peak,
#: the heavy stiff hand, 100 N/m at 50 Hz with 50 ms); never coming back in the contact lost
#: the rest plane where the verified planes stop (the stiffening object at 1000 N/m, beyond the
#: capped plane's reach: 14 conditions of 80). Measured with the fidelity benchmark's 1-D
#: simulator, 2026-11-26: with 1 s, stable with every hand of the box in all 80 stiffening
#: conditions and both local models, and within the JND of the best in 76.
HOLD_BACK_S = 1.0

#: The probe dampers tried, as fractions of the device's damping (B_h,max).
DAMPER_FRACTIONS = (0.0, 0.25, 0.5, 1.0)

#: The least probe damper, as a multiple of K_h T [N*s/m per N/m*s] (:mod:`shared.gains.rest_plane`).
MIN_DAMPER_PER_STIFFNESS_PERIOD = 0.5

#: The frequencies [Hz] over which the damper's felt impedance is matched to the object's.
DAMPER_BAND_HZ = (0.5, 1.0, 2.0, 4.0, 8.0)


# ------------------------------------------------------------------
# The own-response check (shared.gains.own_response)

#: Window [s] of the check: a sample's weight falls by e every window.
WINDOW_S = 2.0

#: |rho - 1| at or below which the object counts as the K_o reported (inside the +/- 5 % the
#: verified plane is checked over, :data:`shared.gains.policy.VERIFIED_RANGE`).
TOLERANCE = 0.04

#: |rho - 1| above which a verdict is withdrawn at once (the hysteresis keeps a contact near the
#: tolerance from switching designs on every patch).
REFUSE_TOLERANCE = 0.05

#: Least standard deviation [N] of the forces in the window for a verdict: a 0.3 N spread on a
#: 1000 N/m object is 0.3 mm of deformation to read the slope from ...
MIN_FORCE_SPREAD_N = 0.3

#: ... or [m] of the deformation they cause (spread / K_o): on a soft object a press deforms it
#: by millimetres with a tenth of a newton (100 N/m: 1 mm is 0.1 N).
MIN_DEPTH_SPREAD_M = 1e-3

#: Largest rms residual of the line, as a fraction of the deformation the force spread causes
#: (spread / K_o): a viscoelastic or strain-stiffening response is not a line.
MAX_RESIDUAL = 0.1

#: The stiffness the check may identify, K' / K_o, lies within this factor of the K_o reported
#: (from half to twice it): further off, the report or the contact is in doubt (another user's
#: push correlated with this one's, a grasp) and the check refuses rather than identify.
IDENTIFY_RANGE = 2.0

#: Time [s] the check must have read the contact before it may identify a stiffness other than
#: the one it holds the object to: a few patches of a viscoelastic press lie on a line of any
#: slope; a cycle of the hand's motion (about 1 Hz) shows the loop the residual refuses.
IDENTIFY_AFTER_S = 1.0

#: ... and the weight of patches (their count, each aged by ``exp(-age / window_s)``) it must
#: hold: three patches around a stalled second are not a reading.
IDENTIFY_MIN_SAMPLES = 5.0

#: Largest share of the force's movement one change between two patches may carry for the
#: check to identify: the largest ``dF^2`` over their sum, both aged like the window
#: (:func:`shared.gains.own_response.update_jumps`). A jump between two held levels carries all of it, spread over two or
#: three patches a half or a third: refused; over four patches or more a quarter or less. At
#: 0.2 the fidelity benchmark's half-second press, read at 20 Hz through the loop, was refused
#: where it is identified at 0.3 (300 N/m, no delay; 100 N/m, 100 ms).
IDENTIFY_MAX_JUMP_SHARE = 0.3

# ------------------------------------------------------------------
# A FEM contact's slow modes (shared.gains.modal_guard, server.gains)

#: How many times longer than the solid alone its slowest modes may ring under a local model,
#: where the design's margin lies beyond what the solid itself does (the bar of
#: :func:`shared.gains.modal_guard.modal_bar`): the liver ball alone decays at 1.08/s, so the
#: design's 1/s would leave 8 % for the whole loop; no gain a user feels keeps it (at the ball's
#: side an uncompensated 0.1 K_o decays at 0.97/s over the box). Twice is the least this bar
#: asks that still refuses the designs that grew there at one and two ticks of delay
#: (docs/fem.md).
MODAL_RING_FACTOR = 2.0

#: Softest K_h the guard recommends, over the design's: the unverified fallback's ratio
#: (:data:`FALLBACK_K_RATIO`). A compensated design keeps ``C_h K_h``, so a held press is felt
#: as designed; what softens is the first touch.
MODAL_GUARD_MIN_SCALE = FALLBACK_K_RATIO

#: Modes of largest dynamic response the server checks a FEM contact's gains on
#: (:meth:`shared.modal_loop.ContactModes.reduced`, the rest static): on the liver sphere (159
#: modes), at its side and top, 0-2 ticks of delay, the designs and softened gains, 6 modes gave
#: the slowest decay over the box within 0.015/s of 40 modes' and never more than 0.001/s faster
#: (12 ranked by static share, the ranking before, were up to 0.019/s faster); a candidate's
#: check over the box's lattice at every tick takes 0.17-0.2 s, against 12 modes' 0.45-0.5 s
#: (2026-11-29, docs/fem.md).
MODAL_CHECK_MODES = 6
