"""A simulated observer of the click-to-find study: a target-aware search, as a person searches for the object.

Weight-free, NumPy/SciPy only. Input: the stimulus a participant sees, an sRGB image ``(H, W, 3)`` float32 in
``[0, 1]`` (or uint8), at the size the study site shows it (``display_deg``: the image height in visual degrees).
The observer sees the image and, optionally, the **background statistics** of the same view: the object-free
render of the same camera (``background``, kept by ``camo study build-stimuli`` next to every rendered set). Those
statistics stand for what a participant knows of the scene's ground -- the distribution of its colours and
textures, its sky and its lit and shaded areas -- as the ideal searcher of Najemnik & Geisler knows its
background's statistics; they are pooled over a 4 deg surround, so they never say where the object is (a place of
the background has the same evidence in both images; only its standing in the regional distribution counts).
Without a background the image's own trimmed statistics serve. The object's mask ``(H, W)`` bool is used
afterwards, to score where the simulated participant clicked (exactly as the site hit-tests a click), so identical
inputs give identical clicks whatever the mask.

The model, and what it follows
------------------------------

A participant of the study knows what they look for: *one object* of a size they learned in the practice trials
(whose outline is revealed after each click), resting in the scene, somewhere in the frame. They move their eyes to
the places that look most like such an object, check each candidate when they look at it, click when they are
convinced, and otherwise go on until the time limit. The model has the architecture of **Guided Search 6.0**
(Wolfe 2021, "Guided Search 6.0: An updated model of visual search", Psychon. Bull. Rev. 28:1060-1092): a
*priority map* guides attention; selected items are *identified* by a noisy decision that can err (false alarms
and misses are both produced by that stage); search ends with a target response or when a quitting signal says
stop -- here the site's hard time limit replaces GS6's adaptive quitting threshold, since the task tells the
participant to keep searching. Eye movements follow the visibility-map logic of Najemnik & Geisler (2005,
"Optimal eye movement strategies in visual search", Nature 434; 2009, Vision Res. 49): evidence is sensed
everywhere at each fixation, with a sensitivity that falls with eccentricity.

1. **Local discriminability** (Rosenholtz 1999, Vision Res. 39; Rosenholtz, Li & Nakano 2007, JoV 7(2)): per
   place, a feature vector -- CIE L*a*b* and the energy of the luminance in four orientations (steerable second
   derivatives of a Gaussian, Freeman & Adelson 1991) -- pooled over a centre (sigma 0.15, 0.3, 0.6 deg), and its
   Mahalanobis distance from the robust (trimmed) distribution of the same features in a Gaussian surround (sigma
   4 deg) of the *background* (the object-free view when given), with one JND (Delta E 2.3) of internal noise per
   feature. The surround is taken on the place's *own ground* (``surround="ground"``, :func:`ground_segments`:
   the object-free view's grounds and sky, k-means on colour; one ground -> the whole surround): on split's
   marble-and-asphalt floor a place on the asphalt is compared with asphalt, not with the mixture of both that a
   pooled surround gives at their border (the same rule for steps 2 and 5). With the object-free view's normals
   and ``surfaces="geometry"`` (an option; :func:`surface_labels`) each ground is split into its surfaces: room's
   floor and its walls, of one colour, are two grounds, so a chair on the floor is compared with the floor. Each scale is z-scored against the
   median and MAD over the ground (Itti, Koch & Niebur 1998's normalisation in spirit): ``D`` in d' units, "how
   unusual for this scene's ground".
2. **Object, not shadow.** Out of direct light the ground is lit by the sky alone: darker, bluer (less red, more
   blue relative to green), with the same pattern or less of it (the shading texture of direct light goes). A place
   as much darker than its surround as a cast shadow is (:data:`SHADOW_FACTOR`: it keeps 15-35 % of the light, a
   glass object ~90 %) whose remaining difference -- redder or yellower chromaticity (log R/G, log B/G of linear
   RGB) and *more* texture energy, in units of the surround's spread -- is within ~2 standard deviations is
   *shadow-like* (:func:`_shadow_residual`; luminance
   change without a matching chromatic change is seen as illumination: Kingdom, Beauce & Hunter 2004, Perception
   33; Kingdom 2008, Vision Res. 48; shadow/reflectance separation: Finlayson, Hordley & Drew 2002, ECCV). Its
   *object evidence* is ``O = (1 - 0.6 S) D`` (``shadow_discount``): photometry alone cannot tell a shadow from a
   dark, bluish or glassy object in the shade, so a shadow-like difference is discounted, not removed. With
   ``shadow_reference="background"`` the darkening is measured against the object-free view at the same place
   (the ratio image with the background render, on a cast shadow's physical range :data:`SHADOW_FACTOR_RATIO`)
   and a shadow-like place is discounted fully: a dark object in the scene's own shade is then not shadow-like,
   but a plain object's face turned from the sun is (docs/results/observer.md).
   **Shape** (``shadow_shape="scales"``, the default; :func:`lying_shape`, :func:`shape_over_sizes`): where
   photometry cannot decide, the outline can. A cast shadow lies on the ground plane -- flattened by perspective,
   stretched along the light, away from its caster -- whereas the objects searched for stand up from the ground
   (Mamassian, Knill & Kersten 1998; Stevens 1981; Biederman et al. 1982). The second moments of the shadow-like
   region around each place (Gaussian windows whose FWHM are the object sizes the study shows, the most decisive
   reading per place: Lindeberg 1998's scale selection) say whether it lies (wider than tall, or elongated off
   the vertical: its discount rises to 1), stands (taller than wide: its discount falls to 0, so an upright dark
   face, a dark object or a glass object that the renderer leaves as dark as a shadow is evidence in full) or
   neither (a blob, or the inside of a shade larger than every window: ``shadow_discount`` as without the cue). With
   the default "surround" reference it reads the image only (the shadow-likeness of each place, against
   the background's pooled 4 deg statistics as in step 1), never the object-free view at the same place; the
   verification's null (step 5) applies the same rule to the object-free view.
   **The ground's own texture under a darkening** (``cast_shadow="texture"``, the default; :func:`cast_shadow_map`):
   with the object-free view, a place darker than that view *at the same place* by a cast shadow's factor
   (:data:`SHADOW_FACTOR_RATIO`) whose fine log-luminance structure is still the ground's (regression slope of the
   image's on the view's, ~1 under a shadow, ~0 where a surface replaces the ground) is ground in shadow, whatever
   its outline or hue, and its object evidence is discounted by that much. A shadow changes the light, not the
   reflectance (Barrow & Tenenbaum 1978; Weiss 2001; Finlayson, Hordley & Drew 2002); texture kept under a
   darkening is the most reliable cue of background-subtraction shadow detectors (Leone & Distante 2007; Sanin,
   Sanderson & Lovell 2012). It is what takes an object's *attached* cast shadow -- which the shape cue can read as
   upright and whose warm interreflected light can defeat the chromaticity test -- off the object evidence, so the
   shadow no longer carries more of it than the body. Read at the finest centre scale and applied at every scale:
   being shadowed ground is a property of the place. With ``cast_shadow="texture_chroma"`` (an option,
   :func:`shadow_chroma_kept`) the darkening must also keep the ground's chromaticity, up to the ambient light's
   own shift (towards the sky's blue or the scene's mean colour), so a tinted see-through object is not ground in
   shadow (Horprasert et al. 1999; Cucchiara et al. 2003).
3. **Priority map** ``G`` (GS6's priority map: top-down guidance by the target template): the object prior of a
   participant who knows the target's *size class* and that it *rests on the ground*. No object rests on the sky
   (:func:`sky_map`: the smooth region at the top and what it encloses -- the sun's glow and disc; Neider &
   Zelinsky 2006: searchers for a ground object hardly look at the sky): ``O`` is set to "typical" there. For each
   object size the study shows (``object_deg``: 10-30 % of the frame width) the mean of ``O`` over a disc of that
   size minus the *second* largest such mean of the 8 discs around it (:func:`_compactness`): a compact thing
   differs from its surround on every side but the one where it touches its own shadow, whereas an edge, a horizon
   or a shadow's border runs through two opposite sides; z-scored per size over the ground, maximum over sizes. A
   cast shadow is evidence that an object is *near* (it touches the ground where its shadow begins): the shadow
   evidence ``S * D``, spread over one object size, adds ``shadow_gain`` of itself to the priority *around* the
   shadow -- not on it, and never to the verification of the shadow itself. **The scene's props** (``props``,
   :func:`scene_props`): the compact things of the object-free view -- a crate, a wall, a ceiling light, and
   whatever the verification (step 5) would accept there, such as room's large grey box -- are
   known as the scene's own furniture, as a participant recognises them at a glance; on them only the evidence
   the object-free view lacks there counts (in the image and in step 5's null), so they neither draw the search
   nor pass verification, nor raise the bar of a target beside them.
4. **Fixations** (Najemnik & Geisler 2005/2009; Itti & Koch 2001): at onset the eyes are at the image centre
   (central fixation bias at onset, Tatler 2007, JoV 7(14)) and the first saccade is planned there without a
   check (so an object at the centre has no head start). At each fixation the observer sees every cell's priority
   with a visibility that falls with eccentricity ``e`` as ``v(e) = 1 / (1 + e / e2_deg)`` (the E2 form, Levi,
   Klein & Aitsebaomo 1985), plus Gaussian noise per look; the next fixation goes to the highest perceived
   priority minus **inhibition of return** (Klein 2000, TICS 4): each past fixation subtracts
   ``ior_strength * exp(-d^2 / 2 ior_radius_deg^2)``.
5. **Verification** at each fixation (GS6's identification stage, a decision that can err): the evidence ``V`` at
   the fixated place -- the largest compactness of ``O`` (step 3's measure, over a foveal 1 deg disc and the
   object sizes) within ``verify_radius_deg`` of the fixation, *as a z against what the background gives around
   that place* (the mean and spread of the background's own compactness over the 4 deg surround on the same
   ground, at least the ground's overall spread: a sunlit patch, a shadow's border or a horizon that the
   background has there raises the bar; the same thing on uniform ground stands out) -- is **accumulated over
   time** (``decision="diffusion"``, :func:`diffusion_decision`): a drift-diffusion decision, Wald's sequential
   probability ratio test in continuous time (Wald 1947; Ratcliff 1978, Psychol. Rev. 85; Palmer, Huk & Shadlen
   2005, JoV 5(5): drift proportional to the stimulus strength), with drift ``k (V - criterion)`` and bounds
   ``+-a`` (:func:`diffusion_parameters`: ``a^2 = decision_time_s``, the mean decision time at the criterion;
   ``k`` such that the probability of the "object" bound is the one-shot rule's ``Phi((V - criterion) /
   verify_noise)``). "Object here": the observer clicks the thing it identified -- from the local peak of ``V``
   up the object evidence to the body's own peak (``click="body"``; saccades and pointing land on a target's
   centre of gravity, Findlay 1982, Vishwanath & Kowler 2003; ``click="core"``, :func:`core_click`: the centre of
   gravity of the connected object evidence there, kept in its core -- measured on the built-in scenes and not
   the default, docs/results/observer.md); a background place that passes is a **false
   verification**, a click off the object, a miss as in the study.
   "Background here": search goes on. So weak evidence near the criterion gives slow decisions and errors both
   ways (false verifications and rejected objects), strong evidence fast, sure ones; misses fall as the object's
   evidence rises (it is verified before many background places have been checked); a hidden object leaves only
   background candidates and long searches. ``decision="threshold"`` is the former one-shot comparison
   ``V + N(0, verify_noise^2) > criterion`` with no decision time (Green & Swets 1966).
6. **Time**: each fixation lasts ``fixation_s`` (encoding and the saccade; about 4 fixations per second in scene
   search, Rayner 1998, Psych. Bull. 124; Henderson 2003) plus its decision time -- longer on places that
   resemble the target, as fixations on target-like distractors are (Hooge & Erkelens 1998; Becker 2011) --;
   ``verify_s`` more on the verified candidate (target fixations are longer than distractor fixations: the
   verification epoch of Castelhano, Pollatsek & Cave 2008, Psychon. Bull. Rev. 15, and Malcolm & Henderson
   2009, JoV 9(11)), then the mouse movement by Fitts' law ``a + b log2(d / w + 1)`` from the image centre
   (Soukoreff & MacKenzie 2004: throughput about 4-5 bit/s). No click within ``time_limit_s`` (the site's 40 s)
   is a timeout.

Every default is justified next to it in :class:`ObserverConfig`. **Calibration**: only the human figures of the
paper's Table I (:data:`PAPER_TABLE_I`) were used: the verification criterion (one of two values tried) against
the human range for plainly visible objects (:data:`HUMAN_VISIBLE`: confusion <= 20 %, mean time 1.5-6 s); every
other constant comes from the sources cited (the decision's time scale from Palmer, Huk & Shadlen 2005; the
grounds' separation from the overlap of two normal distributions; the shape cue's window and thresholds from the
study's object sizes and the geometry of a half-plane -- the cue was made the default after one on/off comparison
on the nine visible cells; the diffusion decision, the own-ground surround, the scene's props and the click on the
body after one comparison each, with the former settings kept as options: ``decision="threshold"``,
``surround="all"``, ``props="none"``, ``click="peak"``, ``prop_test="priority"``, ``cast_shadow="none"``; the
props' core is the verification criterion itself, their extent the 98th percentile of a normal ground); nothing is
fitted to any image metric. The check is not met everywhere: docs/results/observer.md shows predicted and human
figures side by side on the built-in scenes' stimuli, and where and why they part.

Outputs: :func:`simulate_search` (per simulated trial: click, time, found), :func:`predict_stimulus` (probability
found, search-time distribution) and :func:`predicted_table` (per method, in the shape of the study's Table I).
:mod:`study_site.predict` runs it on every stimulus ``camo study build-stimuli`` builds.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from camo_base.errors import CamoError


#: The observer's settings that take one of a few words (the default first).
_CHOICES = {"start": ("centre", "random"), "surround": ("ground", "all"), "decision": ("diffusion", "threshold"),
            "shadow_shape": ("scales", "lying", "none"), "shadow_reference": ("surround", "background"),
            "props": ("scene", "none"), "click": ("body", "thing", "core", "peak"),
            "prop_test": ("verify", "priority"), "cast_shadow": ("texture", "texture_chroma", "none"),
            "surfaces": ("colour", "geometry"), "frame": ("lines", "lines_ratio", "none")}


@dataclass(frozen=True)
class ObserverConfig:
    """The observer's parameters (units in the names: ``_deg`` visual degrees, ``_s`` seconds, d' = z units)."""

    #: Height of the displayed image in visual degrees. The site shows it at 72 % of the viewport height: 576 CSS
    #: px of an 800 px window, ~150 mm on a laptop at ~60 cm is ~14 deg; 680 px on a 24" desktop ~18 deg.
    display_deg: float = 16.0
    #: Resolution of the feature maps (pixels per degree): 16, the study's own display -- its 256 px stimuli shown
    #: at 16 deg -- so the maps keep every detail the image has (8 cycles/deg, well within foveal acuity of ~30-60
    #: c/deg; each candidate is verified with the fovea, step 5). The coarser band a 1.5-5 deg object is found by in
    #: peripheral vision is the centre and surround scales' (in degrees, whatever the grid). The former 10 px/deg
    #: (5 cycles/deg) resampled the stimuli first, and its anti-aliasing blurred a thin outline -- room's chairs,
    #: legs and rails 1-2 image px wide, plain to see -- into the floor's texture: measured on the built-in scenes'
    #: stimuli, docs/results/observer.md ("Thin outlines: the feature grid").
    feature_px_per_deg: float = 16.0
    #: Centre scales (Gaussian sigma, degrees): from texture-element size to a fifth of the smallest object the
    #: study shows (10 % of the frame width = 1.6 deg).
    centre_sigmas_deg: tuple[float, ...] = (0.15, 0.3, 0.6)
    #: Surround (Gaussian sigma, degrees): wide enough that an object (1.6-4.8 deg in the study) is a minority of
    #: it, local enough that two kinds of ground (the split scene) have their own statistics.
    surround_sigma_deg: float = 4.0
    #: Which places make a place's surround (steps 1, 2 and 5). "ground" (default): only those on the same ground
    #: as the place, in a segmentation of the object-free view into its grounds and its sky
    #: (:func:`ground_segments`; without an object-free view, all places); "all": every place within the
    #: surround (the former default; it mixes two grounds where they meet, e.g. split's marble and asphalt, so
    #: that every place near their border was unusual in image and background alike).
    surround: str = "ground"
    #: What tells one ground from another with ``surround="ground"``. "colour" (default): the object-free view's
    #: colour grounds (:func:`ground_segments`). "geometry": those grounds split further into the view's surfaces
    #: (:func:`surface_labels`: floor, walls, ceiling by their normals) where the stimulus set has the object-free
    #: view's normals (``camo study build-stimuli`` renders them; ``camo study surfaces`` adds them to an older
    #: set); without normals the same as "colour". Room's floor, brick walls and ceiling are one colour ground (92 %
    #: of its view 0), so a chair on the floor is compared with the dark walls. Not the default: measured on room's
    #: set, the floor-only surround raises the chairs' D (Transparent view 3: 1.7 -> 4.6) but reads the chairs as
    #: darker than the floor by a shadow's factor, so their object evidence and verification fall (Mean view 3:
    #: verification 6.6 -> 3.6, found 78.5 -> 0 %; room Mean 13.0 -> 33.6 % confused, out of the human range;
    #: Transparent 74.8 -> 74.9 %); meadow's, gravel's and split's grounds are the same either way
    #: (docs/results/observer.md, "Surfaces").
    surfaces: str = "colour"
    #: Internal noise, standard deviation per feature in CIE L*a*b* units: one just-noticeable difference,
    #: Delta E*ab ~ 2.3 (Mahy, Van Eycken & Oosterlinck 1994; Sharma 2003).
    internal_noise: float = 2.3
    #: Floor of the per-image spread (MAD, Mahalanobis units) used to z-score a map: one internal-noise unit, so
    #: a flat image does not turn noise into salience.
    spread_floor: float = 1.0
    #: The object sizes the participant expects (diameter, degrees): the study's objects span 10-30 % of the
    #: frame width (``camo study build-stimuli --object-size``), 1.6-4.8 deg at 16 deg; learned in practice,
    #: whose outlines are revealed. Guidance pools object evidence over discs of these sizes.
    object_deg: tuple[float, ...] = (1.6, 3.2, 4.8)
    #: Share of a shadow's evidence added to the priority of the places within one object size of it ("an object
    #: is near"): half, since a shadow says where to look but not which side of it the object stands.
    shadow_gain: float = 0.5
    #: What "as much darker as a cast shadow" is measured against (step 2). "surround": the pooled 4 deg surround of
    #: the object-free view (or of the image without one; :data:`SHADOW_FACTOR`), discounted by
    #: ``shadow_discount``. "background": the object-free view *at the same place*, when the set has one (the ratio
    #: image with the background render: a cast shadow darkens the ground that is there by a shadow's factor,
    #: :data:`SHADOW_FACTOR_RATIO`, while a dark object standing in the scene's own shade is no darker than the
    #: shaded ground there), discounted fully; the background is only used to discount, and a place the object
    #: leaves unchanged is discounted in neither the image nor the verification's null, so it cannot point at
    #: the object. Without the shape cue (``shadow_shape="none"``) neither won on the built-in scenes' stimuli:
    #: "background" put meadow's three visible baselines in or at the edge of the human range, "surround" gravel's
    #: Mean and Random and split's Random (with "background" a plain box's face turned from the sun -- 36 % of the
    #: light of the gravel behind it, darker than gravel's own cast shadows, 42-47 % -- is discounted as a
    #: shadow). With the shape cue, "surround" put 7 of the 9 cells in the human range (8 with the cue read at the
    #: object sizes, ``shadow_shape="scales"``; docs/results/observer.md), hence the default.
    shadow_reference: str = "surround"
    #: Share of a shadow-like place's difference discounted with the "surround" reference (:data:`SHADOW_DISCOUNT`;
    #: 0 = no shadow analysis, 1 = a shadow-like place is no candidate at all).
    shadow_discount: float = 0.6
    #: The shape cue of step 2 (:func:`lying_shape`): the discount of a shadow-like place scaled by the shape of the
    #: shadow-like region around it -- a region lying on the ground (wider than tall, or elongated off the
    #: vertical, as a cast shadow is: flattened by the ground's foreshortening and stretched along the light) is
    #: discounted fully, an upright one bounded on both sides (taller than wide, as a standing object or its face
    #: turned from the sun is) not at all, a round or unbounded one (a blob, the inside or the straight edge of a
    #: shade larger than the window) by ``shadow_discount``. "scales" (default, :func:`shape_over_sizes`): read
    #: with one window per object size the study shows (FWHM 1.6, 3.2, 4.8 deg), the most decisive reading per
    #: place (Lindeberg 1998's scale selection) -- an object larger than a 1 deg window (gravel's glass box,
    #: 3.1 x 4.6 deg) is read as the upright thing it is; "lying": one 1 deg window (the former default: 7 of the
    #: 9 visible-baseline cells in the human range, 3 with "none"); "none": the shape is not looked at. Measured
    #: on the built-in scenes' stimuli: docs/results/observer.md.
    shadow_shape: str = "scales"
    #: Candidate cell size (degrees): about the foveal radius; the grid the fixations land on.
    cell_deg: float = 0.5
    #: Eccentricity (degrees) at which the visibility of the priority halves. E2 is ~1-3 deg for fine pattern
    #: tasks (Levi et al. 1985; Najemnik & Geisler's 6 c/deg target) and grows with the scale of the stimulus;
    #: the priority map is pooled at object scale (1.6-4.8 deg discs), hence 4 deg.
    e2_deg: float = 4.0
    #: Standard deviation of the noise of one look at the priority map (d'): one unit, the z-scale's own.
    look_noise: float = 1.0
    #: Verification window (degrees, radius around the fixation): about the fovea plus the parafovea, where a
    #: 1.6-4.8 deg object is seen well enough to be identified.
    verify_radius_deg: float = 1.0
    #: Foveal scale (degrees): the smallest candidate the verification considers is a disc of 4 x this (1 deg)
    #: across, and the shadow cue is pooled at this sigma.
    verify_sigma_deg: float = 0.25
    #: Verification criterion, in units of the spread of the background's own evidence around the place (step 5's
    #: regional z). A searcher who checks ~4 places a second for up to 40 s must not take plain ground for the
    #: object (GS6 sets the identification criterion to keep false alarms rare): the object-free views of the
    #: built-in scenes give at most 1.8-6.5 at any place (median over places 0-1.9), so 6 leaves empty ground
    #: unclicked but for the decision noise. 2 and 3 (tried) ended searches on grass within ~1.5 s.
    criterion: float = 6.0
    #: Standard deviation of the verification's decision noise (same units): half the background's spread, so a
    #: place one spread below the criterion still passes now and then (p ~2 %) -- the false verifications that
    #: make misses; their rate falls as the object's evidence rises above the background's.
    verify_noise: float = 0.5
    #: How a fixated candidate is verified (step 5). "diffusion" (default): a drift-diffusion decision, Wald's
    #: sequential probability ratio test in continuous time (Wald 1947; Ratcliff 1978, Psychol. Rev. 85; the
    #: proportional-rate diffusion of Palmer, Huk & Shadlen 2005, JoV 5(5)): the evidence ``V`` is sampled while the
    #: place is fixated and accumulated, with a drift proportional to its distance from the criterion, until it
    #: reaches the "object" or the "background" bound (:func:`diffusion_decision`). Its accept probability is the
    #: one-shot rule's ``Phi((V - criterion) / verify_noise)`` (to within 1 %), but it *takes time*: a place far
    #: from the criterion is decided within ~0.1 s, one near it takes up to ``decision_time_s`` on average -- weak
    #: evidence gives slow decisions and more errors either way, strong evidence fast, sure ones. The fixation lasts
    #: ``fixation_s`` plus that decision time. "threshold": the former one-shot comparison, no decision time (with
    #: ``surround="all"`` it reproduces the former default's figures exactly).
    decision: str = "diffusion"
    #: Mean decision time (seconds) of a place whose evidence sits at the criterion (zero drift): ``a^2`` for a
    #: diffusion with unit noise between bounds at +-``a``. 0.5 s: of the order of the mean decision times near
    #: zero stimulus strength in Palmer, Huk & Shadlen 2005's reaction-time task (reaction times of roughly
    #: 0.8-1 s at 0 % motion coherence, of which ~0.3-0.45 s is non-decision time). Not fitted to anything here.
    decision_time_s: float = 0.5
    #: Seconds per fixation outside the decision (encoding, saccade programming and the saccade itself): 0.25,
    #: the former default's whole fixation (180-275 ms mean fixation in scene search, Rayner 1998, plus ~30 ms per
    #: saccade), kept. With ``decision="diffusion"`` a fixation lasts this plus its decision time (~0.05-0.1 s on
    #: plain ground, up to ``decision_time_s`` and beyond on an ambiguous place), 0.3-0.35 s on plain ground: Rayner
    #: 1998's mean fixation of 330 ms in scene perception, and fixations are longer on places that resemble the
    #: target (Hooge & Erkelens 1998, Vision Res. 38; Becker 2011, JEP:HPP 37). With ``decision="threshold"`` the
    #: whole fixation.
    fixation_s: float = 0.25
    #: Extra dwell on the verified candidate before the hand moves (the verification epoch; target fixations
    #: are a few hundred ms longer than distractor fixations, Castelhano et al. 2008; Malcolm & Henderson 2009).
    verify_s: float = 0.3
    #: Inhibition of return: spatial sigma (degrees; about the attended region, Itti & Koch 2001) and strength
    #: (d'; a place is rarely fixated twice unless it stands far above the rest, as in search of static scenes).
    ior_radius_deg: float = 1.0
    ior_strength: float = 6.0
    #: Fitts' law of the click (Shannon form): intercept (s) and slope (s/bit); mouse throughput ~4-5 bit/s
    #: (Soukoreff & MacKenzie 2004) gives ~0.2 s/bit; the intercept holds the start of the movement. The cursor
    #: starts at the image centre; the target width is ``fitts_width_deg``.
    fitts_a_s: float = 0.3
    fitts_b_s: float = 0.2
    fitts_width_deg: float = 1.0
    #: The study site's time limit per trial (TRIAL_TIME_LIMIT_S).
    time_limit_s: float = 40.0
    #: First fixation: "centre" (the study: onset with the eyes at the screen centre) or "random" (uniform).
    start: str = "centre"
    #: Optional learned map in place of step 1's ``D`` (guidance and verification): a local TorchScript file
    #: (``torch.jit.save``) of a saliency or camouflaged-object-detection network, ``(1, 3, H, W)`` sRGB in [0, 1]
    #: -> ``(1, 1, h, w)`` (or ``(1, h, w)``) scores, higher = more conspicuous; resized to the feature grid and
    #: z-scored like the weight-free map. Never downloaded; "" = the weight-free model.
    saliency_model: str = ""
    #: The scene's props (occluded's crate and brick walls, panorama's pillar and block, room's ceiling light):
    #: "scene" (default) -- the compact things of the object-free view and what is connected to them
    #: (:func:`scene_props`) are known as the scene's own furniture: on them only the object evidence the
    #: object-free view does not have there counts, in the image and in the verification's null, so a prop neither
    #: draws the search nor passes verification nor raises the bar of a target beside it, while a target in front
    #: of a prop keeps what it changes. A participant recognises a crate or a wall as such at a glance (scene gist
    #: and layout before search, Wolfe, Vo, Evans & Greene 2011; objects identified within a fixation, Henderson &
    #: Hollingworth 1999, Annu. Rev. Psychol. 50) and does not check it as the camouflaged object again: recognised
    #: distractors are rejected and their features can be set aside (GS6's identification stage; "templates for
    #: rejection", Arita, Carlisle & Woodman 2012, JEP:HPP 38). The model has no recogniser, so the object-free
    #: view of the framing stands for that recognition (it is not contextual cueing: a participant sees one image
    #: per scene, paper Sec. IV and ``study_site.assign``, so nothing is learned from repeats of a scene). It only
    #: takes evidence away, and only where the object-free view has a compact thing of its own. "none": the former
    #: model (props are searched and verified as candidates like any other place).
    props: str = "scene"
    #: Where a verified candidate is clicked. "thing" (an option, measured and not the default: with the two options
    #: below it puts 14 of the 15 visible cells of gravel, split, room, occluded and panorama in the human range
    #: against the default's 12 -- room's Transparent stays out -- but three property tests of the two options fail,
    #: docs/results/observer.md): as "body", then on up the object evidence *in excess of the shadow evidence*
    #: (``O - S D``, both pooled at the foveal scale) -- onto the part of the candidate that looks more like the
    #: object than like its shadow -- where the body's peak is ground in a cast shadow by the texture test (with an
    #: object-free view: :data:`CLICK_CAST_SHADOW`; without that test split's grey vase and panorama's glass box,
    #: shadow-like in colour all over, were left for the blur of their evidence outside their outline, 25 % each).
    #: A cast shadow is evidence that an object is near, not the object (step 3): where an object's shaded side
    #: meets its own cast shadow the object evidence peaks on the shadow's side of the outline (occluded's torus
    #: with each energy's own noise: 98 % of the clicks of its Mean and Random view 2 a pixel outside the rim), and
    #: the shadow evidence there is larger (8.9 against 4.1-4.6), while on a body without a shadow under it (room's
    #: chairs: shadow evidence ~0.2) the click is the same as "body"'s.
    #: "body" (default): from the peak of the verification evidence up the object evidence ``O`` (pooled
    #: at the foveal scale ``verify_sigma_deg``) to its local maximum -- onto the thing that was identified, not the
    #: contrast peak at its outline: saccades and pointing land near the centre of gravity of a target's body
    #: (Findlay 1982, Vision Res. 22; Vishwanath & Kowler 2003, Vision Res. 43). "peak": the local peak of the verification evidence (the former rule; split's glass vase
    #: was clicked 1 px outside its outline, at its base where the grounds' border and its shadow meet). "core"
    #: (:func:`core_click`): from the body's peak to the centre of gravity of the connected object evidence
    #: (>= :data:`CLICK_EVIDENCE`) holding it, kept in that region's core -- the rule of the literature above taken
    #: literally; measured on the built-in scenes' stimuli it moved as many visible finds off the object as onto
    #: it (10 of 18 visible cells in the human range against 12: the evidence region of a thin or half-shaded object
    #: and of a torus whose attached shadow carries its strongest evidence is not the object's own region at the
    #: pixel scale the site scores), so it is an option, not the default.
    click: str = "body"
    #: Which places of the object-free view are a prop's core (:func:`scene_props`). "verify" (default): those whose
    #: object-sized priority reaches the verification ``criterion`` and, besides, those the verification itself would
    #: accept there (step 5's regional z of the object-free view against its own null, with the props found so far
    #: taken out, at least the ``criterion``; repeated until a round adds none) -- whatever the observer would verify
    #: as an object in the scene without the object is part of the scene, so a large flat prop that stands out only
    #: against its own surround (room's grey box) is known like a crate. "priority": the priority test alone.
    prop_test: str = "verify"
    #: The cast-shadow test against the object-free view (step 2b, :func:`cast_shadow_map`). "texture" (default):
    #: a place that is darker than the object-free view *at the same place* by a cast shadow's factor
    #: (:data:`SHADOW_FACTOR_RATIO`) **and still shows that ground's own fine texture** (the image's fine log
    #: luminance regressed on the background's there: slope ~1 under a shadow, ~0 where an object's surface replaces
    #: the ground) is ground in shadow, whatever its outline: its object evidence is discounted by that
    #: shadow-likeness, fully where both hold fully. This takes an object's attached cast shadow off the object
    #: evidence where the shape cue cannot (occluded's torus: its crescent shadow, taller than wide, read as upright
    #: and carried the strongest object evidence, 5.0 against 1-4 on the torus, so the click landed beside the
    #: torus; room: Ours' chair was clicked on the shadow under its seat, whose warm interreflected light defeats
    #: the chromaticity test). A shadow multiplies the light on the ground and leaves its reflectance -- its
    #: texture -- in place (intrinsic images: Barrow & Tenenbaum 1978; Weiss 2001, ICCV; log-domain illumination
    #: invariance: Finlayson, Hordley & Drew 2002, ECCV); texture kept under a darkening is the most reliable shadow
    #: cue of background-subtraction shadow detectors (Leone & Distante 2007, Pattern Recognit. 40; Sanin, Sanderson
    #: & Lovell 2012, Pattern Recognit. 45, whose comparison ranks large-region texture methods first); and people
    #: see a luminance change that keeps the pattern and its chromaticity as a change of illumination, not of
    #: material (Kingdom 2008, Vision Res. 48). Without a background, or on ground with no texture above the
    #: internal noise, it says nothing (the former analysis alone). "texture_chroma" (an option): the same, and besides
    #: **the ground's own chromaticity is kept** (:func:`shadow_chroma_kept`): a cast shadow takes the direct light away
    #: and leaves the ambient -- the sky's, bluer along the Planckian direction, or the light the scene's own surfaces
    #: send back, of their mean colour -- so the ground's log chromaticity at the place moves only within the cone of
    #: those two directions, while a surface in front of the ground (an amber or red glass, a coloured translucent
    #: object) moves it elsewhere and is not discounted (the brightness-ratio-plus-chromaticity shadow tests of
    #: Horprasert, Harwood & Davis 1999; Cucchiara, Grana, Piccardi & Prati 2003, IEEE PAMI 25(10); Sanin, Sanderson &
    #: Lovell 2012). Grey glass keeps the ground's chromaticity and stays undecided. Measured on the built-in scenes'
    #: sets and not the default (docs/results/observer.md, "Object or its shadow: chromaticity"). "none": the former
    #: model.
    cast_shadow: str = "texture"
    #: Internal noise of the orientation energies, in units of the L* JND (``internal_noise``) times this gain.
    #: 1.0 (default, the former model): the energies get the L* JND itself. :data:`ENERGY_GAIN` (0.52, the energy
    #: channel's RMS response to a unit L* grating at its preferred frequency, so one L* JND *in the energy's own
    #: units*) is the physically consistent value: with it room's thin
    #: chairs (30 L* edges on a floor whose energy varies by ~0.3) stand out, Mean 55 -> 0.3 % and Transparent
    #: 88 -> 50 % confused, occluded's Transparent 26 -> 0 %; with the former click rule (``click="body"``)
    #: occluded's Mean and Random view 2 (a torus whose dark side meets its shadow) were then clicked just outside
    #: the rim (98 % missed), which ``click="thing"`` fixes; with both and ``prop_margin=2`` 14 of 15 visible cells
    #: are in range (default 12), but a cast shadow's outline -- a luminance-only step, like a chair's -- gains
    #: object evidence too: tests/test_observer.py's shadow-reference and shape-cue tests fail (verification 1.5-1.8
    #: on a shadow against their bounds 1.0-1.2; over 21 places of a lying shadow the whole model's median rises
    #: 0.78 -> 1.98), and on meadow's set the plainly visible optimised boxes are clicked on their cast shadows
    #: (Ours 6.9 -> 62.5 % confused), so it is an option (docs/results/observer.md). All of this was measured on the
    #: former 10 px/deg grid; on the display's grid (``feature_px_per_deg=16``) room's wooden chairs are found without
    #: it, and with it and ``prop_margin=2`` the synthetic thin chair of tests/test_observer.py is missed (0 %); the
    #: combination with ``click="thing"`` keeps 13 of 18 visible cells in range there against the default's 17
    #: (panorama's and split's plain objects clicked just outside their outline; docs/results/observer.md).
    energy_gain: float = 1.0
    #: A place of the object-free view is a prop's core (:func:`scene_props`) from ``criterion - prop_margin *
    #: verify_noise``. 0 (default): from the criterion itself. The verification is noisy, so a thing of the scene
    #: two noise units under the criterion is still accepted now and then (Phi(-2) = 2.3 % per look); 2 counts it as
    #: part of the scene. With ``energy_gain=ENERGY_GAIN`` and a margin of 0, room's grey box
    #: (verification 5.8-5.9 against 6) drew 56-65 % of the clicks on views 0 and 3; with 2, none.
    prop_margin: float = 0.0
    #: Step 2d, the object's own lines (:func:`line_map`, :func:`frame_evidence`). ``"lines"``: thin dark lines --
    #: darker than the ground on *both* sides, narrower than :data:`FRAME_LINE_DEG`, holding along their length for
    #: it (a speck or a speckle's gaps are no line), with flanks alike (:func:`flank_contrast`: a line between two
    #: different surfaces is an edge) -- stronger than the object-free view's lines around the place on its own
    #: ground count as object evidence, and a darkening such a line runs on is no cast shadow (Hering's outlined
    #: shadow is seen as a stain). ``"none"`` (default): the former model. Measured on the six built-in sets
    #: (docs/results/observer.md, "The object's own lines"): 18 of 18 visible cells in range (room Mean 0.0 %, room
    #: Transparent 17.5 %, occluded Mean / Random 16.2 / 16.8 %), panorama's Ours box found (7.9 % confused); kept an
    #: option: room Transparent is near the range's edge and Kendall's tau falls on split's detail ratio (-1.00).
    #: ``"lines_ratio"``: the same, each line's depth read as a contrast *ratio* to its flanks (:func:`line_map`'s
    #: ``contrast="ratio"``: the top-hats on log luminance), so a see-through rail that darkens the ground's texture
    #: by a factor has one depth along it over a dark floor and a light one (room's glass chair of view 0: found
    #: 31 -> 100 %), but a dark ground's grain deepens too (panorama's Ours box lost: 7.9 -> 59.9 % confused;
    #: docs/results/observer.md, "Line depth as a contrast ratio").
    frame: str = "none"

    def validate(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name in _CHOICES:
                if v not in _CHOICES[f.name]:
                    allowed = " or ".join(repr(c) for c in _CHOICES[f.name])
                    raise CamoError(f"observer {f.name} must be {allowed}, not {v!r}")
                continue
            if f.name == "saliency_model":
                if v and not Path(v).expanduser().is_file():
                    raise CamoError(f"observer saliency_model: file not found: {v}")
                continue
            vals = v if isinstance(v, tuple) else (v,)
            if not vals or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
                                   for x in vals):
                raise CamoError(f"observer {f.name} must be finite numbers, not {v!r}")
            if f.name == "shadow_discount" and not 0.0 <= v <= 1.0:
                raise CamoError(f"observer shadow_discount must be in [0, 1], not {v!r}")
            may_be_zero = ("fitts_a_s", "shadow_gain", "shadow_discount", "verify_s", "prop_margin")
            if f.name not in may_be_zero and any(x <= 0 for x in vals):
                raise CamoError(f"observer {f.name} must be > 0, not {v!r}")
            if any(x < 0 for x in vals):
                raise CamoError(f"observer {f.name} must be >= 0, not {v!r}")
        if self.saliency_model and self.frame != "none":
            raise CamoError(f"observer frame {self.frame!r} reads the image's own lines, which a learned "
                            "saliency_model replaces: set one or the other")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["centre_sigmas_deg"] = list(self.centre_sigmas_deg)
        d["object_deg"] = list(self.object_deg)
        if self.saliency_model:
            from evaluation.metrics.weights import weights_sha256

            d["saliency_model_sha256"] = weights_sha256(self.saliency_model)
        return d


# --------------------------------------------------------------------------------------------------------------
# features and discriminability
# --------------------------------------------------------------------------------------------------------------


def _as_srgb(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] not in (3, 4) or a.shape[0] < 8 or a.shape[1] < 8:
        raise CamoError(f"observer: expected an (H, W, 3) image of at least 8x8 px, got shape {a.shape}")
    a = a[..., :3]
    if a.dtype == np.uint8:
        return a.astype(np.float32) / 255.0
    a = a.astype(np.float32)
    if not np.isfinite(a).all() or a.min() < -1e-3 or a.max() > 1 + 1e-3:
        raise CamoError("observer: image values must be finite sRGB in [0, 1]")
    return np.clip(a, 0.0, 1.0)


def srgb_to_lab(srgb: np.ndarray) -> np.ndarray:
    """sRGB in [0, 1] ``(..., 3)`` -> CIE L*a*b* (D65), float32: L* in [0, 100], a*, b* roughly [-100, 100]."""
    c = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    m = np.array([[0.4124564, 0.3575761, 0.1804375],
                  [0.2126729, 0.7151522, 0.0721750],
                  [0.0193339, 0.1191920, 0.9503041]], np.float64)
    xyz = c.astype(np.float64) @ m.T / np.array([0.95047, 1.0, 1.08883])
    d = 6.0 / 29.0
    f = np.where(xyz > d ** 3, np.cbrt(xyz), xyz / (3 * d * d) + 4.0 / 29.0)
    lab = np.stack([116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], -1)
    return lab.astype(np.float32)


def _resample(img: np.ndarray, scale: float) -> np.ndarray:
    """Resize ``(H, W, C)`` by ``scale`` (anti-aliased when shrinking)."""
    from scipy import ndimage

    if abs(scale - 1.0) < 1e-6:
        return img
    if scale < 1.0:
        img = ndimage.gaussian_filter(img, (0.5 / scale, 0.5 / scale, 0), mode="reflect")
    h, w = img.shape[:2]
    oh, ow = max(8, int(round(h * scale))), max(8, int(round(w * scale)))
    return ndimage.zoom(img, (oh / h, ow / w, 1), order=1, mode="nearest", grid_mode=True)


def _features(lab: np.ndarray, sigma_c: float) -> np.ndarray:
    """``(7, h, w)``: L*, a*, b* pooled over the centre, and 4 oriented energies (L* units) at that scale."""
    from scipy import ndimage

    g = lambda x, s: ndimage.gaussian_filter(x, s, mode="reflect")  # noqa: E731
    st = max(0.7, sigma_c / 2.0)
    L = lab[..., 0]
    lxx = ndimage.gaussian_filter(L, st, order=(0, 2), mode="reflect") * st * st
    lyy = ndimage.gaussian_filter(L, st, order=(2, 0), mode="reflect") * st * st
    lxy = ndimage.gaussian_filter(L, st, order=(1, 1), mode="reflect") * st * st
    feats = [g(lab[..., k], sigma_c) for k in range(3)]
    for th in (0.0, math.pi / 4, math.pi / 2, 3 * math.pi / 4):
        c, s = math.cos(th), math.sin(th)
        r = c * c * lxx + 2 * c * s * lxy + s * s * lyy
        feats.append(np.sqrt(g(r * r, sigma_c)))
    return np.stack(feats).astype(np.float64)


#: Gain of an orientation-energy channel of :func:`_features` (``sqrt`` of the pooled squared response of a
#: scale-normalised second derivative of a Gaussian, ``st^2 d^2/dx^2``) for a luminance grating of unit amplitude
#: at its preferred frequency (``omega st = sqrt 2``): ``2 / e`` at the peak, its RMS ``sqrt(2) / e`` = 0.52. The
#: internal noise of one JND of L* (``ObserverConfig.internal_noise``) is that many energy units: a feature's noise
#: is one JND *in that feature's own units* (the former model added 2.3 to the energies as to L*, so an edge of
#: 30 L* on a texture of 0.3 energy units -- room's chairs -- was within about one noise unit of the floor).
ENERGY_GAIN = math.sqrt(2.0) / math.e


def _feature_noise(noise: float, k: int, gain: float | None = None) -> np.ndarray:
    """``(k,)`` internal noise per feature of :func:`_features` (3 colour channels, then orientation energies):
    ``noise`` for the colour, ``noise * gain`` for the energies (``gain``: ``ObserverConfig.energy_gain``, default
    :data:`ENERGY_GAIN`)."""
    g = ENERGY_GAIN if gain is None else gain
    return np.array([noise] * 3 + [noise * g] * (k - 3))[:k]


def _distance(f: np.ndarray, mu: np.ndarray, cov: np.ndarray, noise: float | np.ndarray) -> np.ndarray:
    """Mahalanobis distance of ``f`` ``(k, h, w)`` from mean ``mu`` and covariance ``cov`` ``(k, k, h, w)`` (or
    ``(k,)`` / ``(k, k)`` for one distribution), internal noise ``noise``^2 added to the variances (a number, or
    one per feature: :func:`_feature_noise`)."""
    k = f.shape[0]
    diff = np.moveaxis(f - mu.reshape(mu.shape + (1, 1)[: f.ndim - mu.ndim]), 0, -1)[..., None]
    c = cov.copy()
    nz = np.broadcast_to(np.asarray(noise, np.float64), (k,)).reshape((k,) + (1,) * (c.ndim - 2))
    c[range(k), range(k)] = np.maximum(c[range(k), range(k)], 0.0) + nz * nz
    if c.ndim > 2:
        c = np.moveaxis(c, (0, 1), (-2, -1))
    sol = np.linalg.solve(np.broadcast_to(c, diff.shape[:-2] + (k, k)), diff)
    return np.sqrt(np.maximum((diff * sol).sum(axis=(-2, -1)), 0.0))


#: Share of the image left out of the background statistics as outliers (the object covers at most ~10 % of a
#: study stimulus; one-step reweighting as in Rousseeuw's reweighted MCD estimator).
TRIM = 0.10


def _wide_blur(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of a 2-D map with a wide ``sigma`` (pixels), zero outside the image (so a ratio of two blurs
    is a normalised convolution: a place near the border gets the statistics of the pixels that exist, not of a
    mirrored copy of itself -- with mirroring an object near a corner became part of its own surround and was
    found less often than the same object at the centre). Computed on a grid ``q = sigma // 8`` times coarser
    (block means, blur by ``sigma / q``, bilinear back): the surround statistics are smooth at that scale and the
    full-resolution filter of a 4 deg surround took ~95 % of the observer's time (measured on 160 px maps)."""
    from scipy import ndimage

    q = int(sigma // 8)
    if q <= 1:
        return ndimage.gaussian_filter(x, sigma, mode="constant", cval=0.0)
    h, w = x.shape
    hh, ww = -(-h // q) * q, -(-w // q) * q
    xp = np.pad(x, ((0, hh - h), (0, ww - w)), mode="constant")
    small = xp.reshape(hh // q, q, ww // q, q).sum(axis=(1, 3)) / q / q
    small = ndimage.gaussian_filter(small, sigma / q, mode="constant", cval=0.0)
    big = ndimage.zoom(small, q, order=1, mode="nearest", grid_mode=True)
    return big[:h, :w]


def _norm_blur(x: np.ndarray, sigma: float, wide: bool = True) -> np.ndarray:
    """Normalised Gaussian mean of ``x`` over the pixels inside the image (``sigma`` in pixels)."""
    from scipy import ndimage

    if wide:
        return _wide_blur(x, sigma) / np.maximum(_wide_blur(np.ones_like(x), sigma), 1e-9)
    one = np.ones_like(x)
    return ndimage.gaussian_filter(x, sigma, mode="constant") / np.maximum(
        ndimage.gaussian_filter(one, sigma, mode="constant"), 1e-9)


def _seg_blur(x: np.ndarray, sigma: float, seg: np.ndarray | None) -> np.ndarray:
    """Normalised Gaussian mean of ``x`` over the pixels inside the image *on the same ground* as each place
    (``seg``: :func:`ground_segments` labels ``(h, w)``; None = one ground, :func:`_norm_blur`)."""
    if seg is None or seg.max() == 0:
        return _norm_blur(x, sigma)
    out = np.empty_like(x, dtype=np.float64)
    for k in range(int(seg.max()) + 1):
        m = (seg == k).astype(np.float64)
        mean = _wide_blur(x * m, sigma) / np.maximum(_wide_blur(m, sigma), 1e-9)
        out[seg == k] = mean[seg == k]
    return out


def _mahalanobis(f: np.ndarray, sigma_s: float, noise: float, fb: np.ndarray | None = None,
                 seg: np.ndarray | None = None) -> np.ndarray:
    """Per ground of ``seg`` (:func:`ground_segments`; None = one ground): :func:`_mahalanobis_one` with the
    surround taken on that ground only, for the places standing on it."""
    if seg is None or seg.max() == 0:
        return _mahalanobis_one(f, sigma_s, noise, fb)
    out = np.empty(f.shape[1:])
    for k in range(int(seg.max()) + 1):
        on = seg == k
        out[on] = _mahalanobis_one(f, sigma_s, noise, fb, on)[on]
    return out


def _mahalanobis_one(f: np.ndarray, sigma_s: float, noise: float, fb: np.ndarray | None = None,
                     on: np.ndarray | None = None) -> np.ndarray:
    """Distance of each place's features from the background distribution of its Gaussian-weighted surround.

    The background statistics are robust: the places whose features are global outliers (the top :data:`TRIM`
    of the distances from the whole image's mean and covariance) are left out of every surround, so a large
    object does not become its own background. Where a surround is almost all outliers, the whole image's
    trimmed statistics fill in."""
    f_img, f = f, (f if fb is None else fb)  # the statistics come from the background when there is one
    k = f.shape[0]
    sel = np.ones(f.shape[1:], bool) if on is None else on  # the ground whose statistics are taken
    flat = f[:, sel]
    m0 = _distance(f, flat.mean(1), np.cov(flat), noise)
    w = ((m0 <= np.quantile(m0[sel], 1.0 - TRIM)) & sel).astype(np.float64)
    fw = f.reshape(k, -1)[:, w.reshape(-1) > 0]
    mu_g, cov_g = fw.mean(1), np.cov(fw)
    eps = 0.05  # weight of the whole image's trimmed statistics in every surround
    g = lambda x: _wide_blur(x, sigma_s)  # noqa: E731
    g1 = eps * g(np.ones_like(w))  # zero outside the image: the global share is the same everywhere
    den = g(w) + g1
    mu = np.stack([(g(w * f[i]) + g1 * mu_g[i]) / den for i in range(k)])
    cov = np.empty((k, k) + f.shape[1:])
    for i in range(k):
        for j in range(i, k):
            second = (g(w * f[i] * f[j]) + g1 * (cov_g[i, j] + mu_g[i] * mu_g[j])) / den
            cov[i, j] = cov[j, i] = second - mu[i] * mu[j]
    return _distance(f_img, mu, cov, noise)


_MODELS: dict[tuple, Any] = {}


def load_saliency_model(path: str | Path):
    """A TorchScript saliency network from a local file (cached by path, size and modification time)."""
    import torch

    p = Path(path).expanduser()
    if not p.is_file():
        raise CamoError(f"observer saliency_model: file not found: {p}")
    st = p.stat()
    key = (str(p.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _MODELS:
        try:
            m = torch.jit.load(str(p), map_location="cpu")
        except Exception as exc:  # torch raises RuntimeError / ValueError / pickle errors for a bad file
            raise CamoError(f"observer saliency_model {p}: not a TorchScript file "
                            f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
        m.eval()
        _MODELS[key] = m
    return _MODELS[key]


def _zscore(m: np.ndarray, floor: float, where: np.ndarray | None = None) -> np.ndarray:
    """``m`` in units of its robust spread (median, 1.4826 MAD, at least ``floor``) over the places ``where``
    (bool, default all)."""
    v = m if where is None or not where.any() else m[where]
    med = float(np.median(v))
    return (m - med) / max(1.4826 * float(np.median(np.abs(v - med))), floor)


def learned_map(srgb: np.ndarray, config: ObserverConfig) -> np.ndarray:
    """``D`` from the TorchScript network of ``config.saliency_model`` at the feature resolution (z-scored)."""
    import torch

    from scipy import ndimage

    scale = config.display_deg * config.feature_px_per_deg / srgb.shape[0]
    img = _resample(srgb, scale)
    model = load_saliency_model(config.saliency_model)
    x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None].float()
    try:
        with torch.no_grad():
            y = model(x)
    except Exception as exc:  # a network that does not take this input
        raise CamoError(f"observer saliency_model: the network failed on a {img.shape[1]}x{img.shape[0]} image "
                        f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
    y = np.asarray(y.detach().cpu().numpy(), np.float64).squeeze()
    if y.ndim != 2 or not np.isfinite(y).all():
        raise CamoError(f"observer saliency_model: expected one finite (h, w) map, got shape {tuple(y.shape)}")
    h, w = img.shape[:2]
    y = ndimage.zoom(y, (h / y.shape[0], w / y.shape[1]), order=1, mode="nearest", grid_mode=True)[:h, :w]
    return _zscore(y, 1e-6 + 1e-3 * float(np.std(y))).astype(np.float32)


#: Share of a place's difference discounted where it looks like a cast shadow (darker, no chromaticity change but
#: towards the sky's blue): half -- photometry alone cannot tell a shadow from a dark, bluish object (a glass or
#: metal object in the shade looks the same; measured on the meadow stimuli, discounting it all hid them).
SHADOW_DISCOUNT = 0.6  # the default of ObserverConfig.shadow_discount
#: Light left in a cast shadow relative to the sunlit surround, from which a darker place starts to count as
#: shadow-like (first) and counts fully (second). On a clear day the direct sun brings ~65-85 % of the light on
#: the ground, so a cast shadow keeps 15-35 % (a ratio the pooled surround, which includes part of the shadow,
#: dilutes towards ~0.5); a glass or clear object in front of the ground passes ~85-92 % (Fresnel loss ~4 % per
#: surface), so it is not taken for a shadow.
SHADOW_FACTOR = (0.8, 0.5)
#: The same with ``shadow_reference="background"``: the light left against the object-free view of the same place,
#: not diluted by a pooled surround, so the physical range of a daylight cast shadow applies directly (it keeps
#: 15-35 %): shadow-like from 50 %, fully from 30 %. On the built-in scenes' stimuli the objects' cast shadows keep
#: 23-47 % (measured against the backgrounds); a glass object ~90 %.
SHADOW_FACTOR_RATIO = (0.5, 0.3)
#: A place is shadow-like when what a shadow cannot explain (:func:`_shadow_residual`) is within about this many
#: standard deviations of its surround (Gaussian fall-off).
SHADOW_RESIDUAL = 2.0
#: Units of the log features: 50 ln(.), so the internal noise (2.3) is a ratio change of ~4.6 % -- a Weber
#: fraction for luminance contrast and about the threshold for a chromaticity ratio in natural scenes.
LOG_UNITS = 50.0
#: Dark floor added to linear RGB before the logs (~ sRGB 0.0013, a third of the darkest 8-bit step): it keeps
#: the ratios finite on black without breaking their invariance on dark ground (1e-3 did, measured).
LOG_FLOOR = 1e-4


def _gauss(x: np.ndarray, sigma: float) -> np.ndarray:
    from scipy import ndimage

    return ndimage.gaussian_filter(x, sigma, mode="reflect")


@dataclass
class Maps:
    """The observer's maps at the feature resolution ``(h, w)`` (``h = display_deg * feature_px_per_deg``), d'."""

    d: np.ndarray  # discriminability D (step 1), max over centre scales
    d_inv: np.ndarray  # what a shadow cannot explain (step 2, :func:`_shadow_residual`), z-scored
    shadow: np.ndarray  # shadow evidence S * D (step 2; S includes the darker-than-surround ramp), >= 0
    obj: np.ndarray  # object evidence O (step 2)
    guidance: np.ndarray  # priority G (step 3)
    verify: np.ndarray  # verification evidence V (step 5): compactness of O, max over the candidate sizes
    sky: np.ndarray | None = None  # bool: the sky (:func:`sky_map`), where no object rests
    cast: np.ndarray | None = None  # ground in a cast shadow (step 2b, :func:`cast_shadow_map`), [0, 1], or None
    lines: np.ndarray | None = None  # the two-sided lines' evidence (step 2d, :func:`frame_evidence`, z), or None


def _log_image(srgb: np.ndarray) -> np.ndarray:
    """``(h, w, 3)``: ``LOG_UNITS * ln`` of the linear luminance and of the linear R/G and B/G ratios (with a dark
    floor :data:`LOG_FLOOR`): a shadow (linear radiance times a factor) shifts the first channel only, in every
    regime (unlike L*a*b*, whose cube root turns linear near black)."""
    c = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4).astype(np.float64) + LOG_FLOOR
    y = 0.2126729 * c[..., 0] + 0.7151522 * c[..., 1] + 0.0721750 * c[..., 2]
    return LOG_UNITS * np.stack([np.log(y), np.log(c[..., 0] / c[..., 1]), np.log(c[..., 2] / c[..., 1])], -1)


def _shadow_residual(lf: np.ndarray, f: np.ndarray, sigma_s: float, noise: float,
                     lfb: np.ndarray | None = None, fb: np.ndarray | None = None,
                     seg: np.ndarray | None = None, gain: float = 1.0) -> np.ndarray:
    """The part of a place's difference from its surround that a cast shadow cannot explain, in units of the
    surround's spread (internal noise added). ``lf``: log features ``(7, h, w)`` (ln luminance, ln R/G, ln B/G,
    ...; :func:`_log_image`); ``f``: the L*a*b* features (:func:`_features`).

    Out of direct light the ground is lit by the sky alone: darker and bluer (less red, more blue relative to
    green), while its texture goes on -- the same pattern at a lower light level, so the same contrast relative to
    the local luminance (orientation energy / (L* + 16)). A shadow explains chromaticity shifts towards blue and
    nothing else: redder or yellower, and any change of relative texture energy (a flat object on textured
    ground, or a new pattern), count. Luminance is left out entirely."""
    def parts(lf, f):  # (feature, sign, internal noise in its units)
        return [(lf[1], 1.0, noise), (lf[2], -1.0, noise)] + [(f[i], 1.0, noise * gain) for i in range(3, 7)]

    own = parts(lf, f)
    ref = own if lfb is None else parts(lfb, fb)
    out = np.zeros(f.shape[1:])
    for (x, sign, nz), (xb, _, _) in zip(own, ref):
        mu = _seg_blur(xb, sigma_s, seg)
        sd = np.sqrt(np.maximum(_seg_blur(xb * xb, sigma_s, seg) - mu * mu, 0.0) + nz * nz)
        z = (x - mu) / sd
        out += (np.maximum(sign * z, 0.0) if sign else z) ** 2
    return np.sqrt(out)


def cast_shadow_map(logimg: np.ndarray, log_bg: np.ndarray, sigma_c: float, cfg: ObserverConfig) -> np.ndarray:
    """``(h, w)`` in [0, 1]: how much each place looks like the object-free view's own ground in a cast shadow
    (step 2b, ``ObserverConfig.cast_shadow``), from the log images of the stimulus and of its object-free view
    (:func:`_log_image`, ``(h, w, 3)`` on the feature grid) at the centre scale ``sigma_c`` (px).

    Two conditions, multiplied:

    * *darker by a shadow's factor at this very place*: the light kept against the object-free view, pooled over
      the centre, on the ramp :data:`SHADOW_FACTOR_RATIO` (shadow-like from 50 % of the light, fully from 30 %; a
      daylight cast shadow keeps 15-35 %, the built-in scenes' cast shadows 23-47 %, a glass object ~90 %);
    * *the ground's own texture is still there*: the fine structure of log luminance (each log image minus its
      median over the finest centre scale, ``centre_sigmas_deg[0]``: an edge-preserving smoother, so a shadow's own
      outline -- a step, or a band wider than half the window -- is not taken for texture, Tukey 1977) of the
      image regressed on the object-free view's at the same place, over the foveal window (``verify_sigma_deg``),
      the view's variance floored at the internal noise (``internal_noise``, :data:`LOG_UNITS`): ``t = cov(i, b) /
      max(var(b), noise^2)``, clipped to [0, 1]. Under a shadow the image is the ground times a smooth factor, so
      its log is the ground's plus a constant and the slope is ~1 (noise in the darkened image does not bias a
      slope; the loss of the direct light's shading of a rough ground lowers it); an object's surface -- a flat
      colour, a texture of its own, glass that refracts the ground elsewhere -- leaves it near 0. On ground without
      texture above the noise no slope can be read and nothing is discounted. Measured on the 120 formal stimuli
      built from the current-default runs (docs/results/observer.md): median ``t`` over the object's pixels 0.08
      (per method 0.04-0.37), the map there 0 (at most 0.24, on room's see-through chair, which shows the floor);
      over the places within 0.7 deg of the object and darker than the view by half (its cast shadow and
      penumbra) ``t`` 0.41, the map 0.13, up to 0.8. The stimulus and its object-free view share their sampler's
      random numbers (``camo evaluate``'s common random numbers), so unchanged ground gives ``t`` ~1 and render
      noise does not count against a shadow; with pixel noise of its own in the image (independent, half the
      texture's contrast) a synthetic shadow still gives 0.81 (tests/test_observer.py). It needs the object-free
      view to be the *same framing*: against another camera's view ``t`` is ~0 everywhere and nothing is
      discounted.

    The mask is never read; the object-free view is the same one that gives the surround statistics."""
    from scipy import ndimage

    ppd = cfg.feature_px_per_deg
    drop = _gauss(log_bg[..., 0] - logimg[..., 0], sigma_c) / LOG_UNITS  # ln(background / image) at the place
    lo, hi = -math.log(SHADOW_FACTOR_RATIO[0]), -math.log(SHADOW_FACTOR_RATIO[1])
    ramp = np.clip((drop - lo) / (hi - lo), 0.0, 1.0)
    # the fine structure of each log image: minus an edge-preserving median over the finest centre scale, so that
    # a shadow's own outline (a step, or a band as narrow as the median window's half) is not taken for texture
    size = 2 * int(math.ceil(cfg.centre_sigmas_deg[0] * ppd)) + 1
    fi = logimg[..., 0] - ndimage.median_filter(logimg[..., 0], size=size, mode="nearest")
    fb = log_bg[..., 0] - ndimage.median_filter(log_bg[..., 0], size=size, mode="nearest")
    win = max(cfg.verify_sigma_deg * ppd, sigma_c)
    # the slope of the image's fine structure on the ground's; the ground's variance floored at the internal noise
    # (no texture above it: no slope can be read, nothing is discounted)
    t = _gauss(fi * fb, win) / np.maximum(_gauss(fb * fb, win), cfg.internal_noise ** 2)
    out = ramp * np.clip(t, 0.0, 1.0)
    if cfg.cast_shadow == "texture_chroma":
        out = out * shadow_chroma_kept(logimg, log_bg, win, cfg.internal_noise)
    return out


#: The direction in (ln R/G, ln B/G) along which a daylight illuminant moves as it gets bluer (sun to sky): by
#: Wien's approximation of Planck's law a blackbody's log chromaticities are linear in 1/T, with slopes
#: proportional to ``1/lambda_k - 1/lambda_G`` (Finlayson, Hordley, Lu & Drew 2006, IEEE PAMI 28(1), the
#: illuminant-invariant direction), here for the sRGB primaries' dominant wavelengths 610, 540 and 450 nm
#: (towards higher T: less red, more blue). Unit vector.
PLANCK_DIRECTION = tuple((lambda v: (v / np.linalg.norm(v)).tolist())(np.array([1 / 610 - 1 / 540, 1 / 450 - 1 / 540])))


def shadow_chroma_kept(logimg: np.ndarray, log_bg: np.ndarray, sigma: float, noise: float) -> np.ndarray:
    """``(h, w)`` in [0, 1]: whether the log chromaticity of the image at each place is what a cast shadow leaves of
    the object-free view's there (``ObserverConfig.cast_shadow="texture_chroma"``). Inputs: the log images of
    :func:`_log_image` ``(h, w, 3)`` (channels 1 and 2: ``LOG_UNITS`` ln R/G and ln B/G of linear RGB), pooled
    with a Gaussian of ``sigma`` px; ``noise``: the internal noise in those units (2.3: a ratio change of ~4.6 %).

    A shadow removes the direct light and keeps the ambient, so the ground at the place changes chromaticity by
    the ambient's chromaticity relative to the whole light's, in one of two directions or a mix of them: towards
    the sky's blue (daylight: less red, more blue relative to green; Nadimi & Bhanu 2004, IEEE PAMI 26(8)) or
    towards the colour of the scene's own surfaces, whose interreflected light is the ambient indoors and under a
    canopy (mutual illumination: Funt, Drew & Ho 1991, IJCV 6; Langer 1999, "When shadows become interreflections",
    IJCV 34) -- read as the mean log chromaticity of the object-free view's ground, the light the scene sends
    back under a neutral illuminant. A change of the ground's chromaticity inside the cone of those two directions
    (or none) is a shadow's; what lies outside it -- an amber glass on green grass, a red one on any ground but a
    red one -- is a surface's. Its distance from the cone, in units of ``noise``, makes the place shadow-like by
    ``exp(-z^2 / 2 SHADOW_RESIDUAL^2)`` (the fall-off of :func:`_shadow_residual`). This is the chromaticity test
    of background-subtraction shadow detectors (brightness ratio plus chromaticity: Horprasert, Harwood & Davis
    1999; Cucchiara, Grana, Piccardi & Prati 2003, IEEE PAMI 25(10); the chromaticity family of Sanin, Sanderson &
    Lovell 2012, Pattern Recognit. 45) with the ambient's colour taken from the scene instead of a fixed
    tolerance. A dark ambient of the ground's own colour (an orange floor in an orange room) leaves a tinted
    object of that colour undecided: it is then read as a shadow, as with the texture test alone. The mask is
    never read."""
    dr = _gauss(logimg[..., 1] - log_bg[..., 1], sigma)
    db = _gauss(logimg[..., 2] - log_bg[..., 2], sigma)
    d = np.stack([dr, db], -1)
    sky_dir = np.array(PLANCK_DIRECTION)
    mean = np.array([float(np.mean(log_bg[..., 1])), float(np.mean(log_bg[..., 2]))])
    dirs = [sky_dir] + ([mean / np.linalg.norm(mean)] if np.linalg.norm(mean) > noise else [])
    # distance of each change from the convex cone spanned by the directions (inside: 0)
    dist = np.linalg.norm(d, axis=-1)  # the apex: no change at all
    for u in dirs:
        along = np.maximum(d @ u, 0.0)
        dist = np.minimum(dist, np.linalg.norm(d - along[..., None] * u, axis=-1))
    if len(dirs) == 2:
        m = np.stack(dirs, -1)  # d = m @ (a, b): inside the cone where a, b >= 0
        if abs(np.linalg.det(m)) > 1e-9:
            ab = d @ np.linalg.inv(m).T
            dist = np.where((ab >= 0).all(-1), 0.0, dist)
    return np.exp(-0.5 * (dist / noise) ** 2 / SHADOW_RESIDUAL ** 2)


#: Length of the linear structuring elements of :func:`line_map` (deg): 0.3, twice the finest centre scale's sigma;
#: a dark line narrower than this (a chair's leg or rail of 1-3 px at 16 px/deg) is filled by a closing across it.
FRAME_LINE_DEG = 0.3


def _line_footprint(theta: float, length: int) -> np.ndarray:
    """``(length, length)`` bool: a digital line segment of ``length`` px through the centre at angle ``theta``."""
    r = length // 2
    m = np.zeros((length, length), bool)
    for t in np.linspace(-r, r, 4 * length):
        m[int(round(r - t * math.sin(theta))), int(round(r + t * math.cos(theta)))] = True
    return m


def _line_tophats(lum: np.ndarray, length_px: int, contrast: str = "difference") -> tuple[np.ndarray, np.ndarray]:
    """The line strength of :func:`line_map` ``(h, w)`` and the index (0-3: 0, 45, 90, 135 deg) of the orientation
    whose structuring element runs *across* the line there (the one whose top-hat is largest: the closing across a
    line fills it). ``contrast``: :func:`line_map`'s."""
    from scipy import ndimage

    if contrast not in LINE_CONTRASTS:
        raise ValueError(f"line contrast {contrast!r}: one of {', '.join(LINE_CONTRASTS)}")
    length = max(3, int(length_px) | 1)  # odd, at least 3 px
    if contrast == "ratio":  # differences of log luminance, in L* units at RATIO_REF_L (L* floored at RATIO_FLOOR_L)
        lum = (RATIO_REF_L + 16.0) * np.log((np.maximum(lum, RATIO_FLOOR_L) + 16.0) / (RATIO_FLOOR_L + 16.0))
    feet = [_line_footprint(a, length) for a in LINE_ANGLES]
    dark = np.stack([ndimage.grey_closing(lum, footprint=f, mode="nearest") - lum for f in feet])
    light = np.stack([lum - ndimage.grey_opening(lum, footprint=f, mode="nearest") for f in feet])
    n = len(feet)

    def along(t: np.ndarray) -> np.ndarray:
        # the depth each orientation's element sees across a line, over the orientations' smallest -- kept only where
        # it holds along the line for the element's length (a grey opening with the element perpendicular to the
        # one that sees it: Soille & Talbot 2001's directional opening). A line is longer than the element; the dark
        # gaps of a speckle (a caustic's or a sparse render's bright grains on a dark shadow) are filled across by
        # one orientation at one pixel and by another at the next, so they read 0 (panorama's Ours box: its shadow's
        # grains read as lines stronger than the box, 93 % of clicks on them). A line whose depth holds along it at
        # least at :data:`LINE_HOLDS` of its depth here keeps its full depth: a glass chair's rail darkens the
        # floor's own texture by a factor, so its depth varies along it, and the opening's minimum alone thinned its
        # frame until the click fell between its lines (synthetic glass chairs in a quadrant: found 0-3 %)
        s = t - t.min(0)
        out = []
        for k in range(n):
            o = ndimage.grey_opening(s[k], footprint=feet[(k + n // 2) % n], mode="nearest")
            out.append(np.where(o >= LINE_HOLDS * s[k], s[k], o))
        return np.stack(out)

    dark, light = along(dark), along(light)
    sd, sl = dark.max(0), light.max(0)
    across = np.where(sd >= sl, dark.argmax(0), light.argmax(0))
    return np.maximum(sd, sl), across


#: :func:`line_map`: a line keeps its full depth at a place where its depth holds along it, for the element's length,
#: at least at this share of the depth there; elsewhere it keeps only what holds (the directional opening). Chosen,
#: like the verification criterion, against the human range for plainly visible objects -- of 1 (the opening alone:
#: room's glass chair of view 0 and synthetic glass chairs in a quadrant lost, 24 % confused), 0.5 (panorama's
#: Ours box of view 1 lost: the ground's own lines back in its ring) and 0.75 tried on the built-in scenes'
#: stimuli (docs/results/observer.md, "The object's own lines"); not fitted to any metric.
LINE_HOLDS = 0.75
#: The 4 orientations of :func:`line_map`'s structuring elements (radians).
LINE_ANGLES = (0.0, math.pi / 4, math.pi / 2, 3 * math.pi / 4)


def line_map(lum: np.ndarray, length_px: int, contrast: str = "difference") -> np.ndarray:
    """``(h, w)`` >= 0: the strength of thin *lines* in ``lum`` (``(h, w)``, L* units), dark or light: the black
    top-hat (grey closing minus the image: Serra 1982, Soille 2003) with a linear structuring element of
    ``length_px`` in each of 4 orientations, largest minus smallest over the orientations, and the same of the
    white top-hat (the image minus its opening: a light line, a glint along a rim), the larger of the two. A closing across a dark line narrower
    than the element fills it (the largest top-hat: the line's depth below both its sides); the closing along the
    line leaves it (the smallest: 0), so a line keeps its depth. A dark speck is filled by every orientation
    (largest = smallest: 0) and a step -- a cast shadow's outline, a horizon -- by none (a closing keeps a monotone
    edge: 0), so neither is a line. A line is also longer than the element: each orientation's depth counts only as
    far as it holds along the line for the element's length (a directional opening, Soille & Talbot 2001, IEEE PAMI
    23; in full where it holds at :data:`LINE_HOLDS` of the depth), so the gaps of a speckle -- a dark ground strewn
    with bright grains, filled across by one orientation at one pixel and by another at the next -- read little
    or nothing. SciPy's grey closing and opening; no learned part.

    ``contrast``: ``"difference"`` (default) reads depths in L*. ``"ratio"``: the depth as a contrast ratio -- the
    top-hats on the log of luminance, ``(RATIO_REF_L + 16) x ln((L* + 16) / (RATIO_FLOOR_L + 16))`` (CIE
    L* = 116 Y^(1/3) - 16 above its linear toe, so this is ``(RATIO_REF_L + 16) / 3 x ln Y`` plus a constant, with
    slope 1 at L* = :data:`RATIO_REF_L`; L* floored at :data:`RATIO_FLOOR_L`): a line that darkens its ground by a
    factor ``f`` reads ``(RATIO_REF_L + 16) / 3 x ln(1 / f)`` whatever the ground's level, so a see-through rail
    over a textured floor keeps one depth along it, where the difference of L* follows the floor's level (Weber's
    law for contrast: Whittle 1994; a transparent layer's multiplicative darkening: Metelli 1974)."""
    return _line_tophats(lum, length_px, contrast)[0]


#: :func:`line_map`'s ``ratio``: L* below this is read as this (a floor under the log: the darkest grounds' noise is
#: not a contrast), and the L* at which the log's scale is one L* per L* (mid-grey: a ratio reads there as in L*).
#: Set by these two meanings, not tuned: the option was run once with them (docs/results/observer.md).
RATIO_FLOOR_L = 10.0
RATIO_REF_L = 50.0
#: :func:`line_map`'s ``contrast`` values.
LINE_CONTRASTS = ("difference", "ratio")


#: Flank features of :func:`flank_contrast`: the centre's Gaussian (px of the feature grid) over which each flank's
#: L*a*b* mean and L* spread (its texture) are read -- 1 px, a third of the flank offset, so a flank reads the
#: surface beside the line and not the line itself.
FLANK_SIGMA_PX = 1.0


def _shifted(a: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``a`` ``(h, w, ...)`` read at ``(y + dy, x + dx)``, the border continued."""
    h, w = a.shape[:2]
    yi = np.clip(np.arange(h) + dy, 0, h - 1)
    xi = np.clip(np.arange(w) + dx, 0, w - 1)
    return a[yi][:, xi]


def flank_contrast(lab: np.ndarray, across: np.ndarray, offset_px: int) -> np.ndarray:
    """``(h, w)`` >= 0: how different the two flanks of the line through each place are -- the Euclidean distance
    between the surfaces ``offset_px`` to either side of it, perpendicular to the line (along ``across``, the index
    into :data:`LINE_ANGLES` of :func:`_line_tophats`), each read as its L*a*b* mean and its L* spread over a
    Gaussian of :data:`FLANK_SIGMA_PX` (colour and texture, L* units). A frame's rail or a chair's leg has the same
    ground on both sides (small); a cast shadow's sliver hugging its caster (the object on one side, lit ground on
    the other) and the dark line where an object's base meets its shadow (the object, the shadow) have two
    different surfaces on their two sides (large). ``lab`` ``(h, w, 3)``."""
    from scipy import ndimage

    s = FLANK_SIGMA_PX
    mean = np.stack([ndimage.gaussian_filter(lab[..., c], s, mode="nearest") for c in range(3)], -1)
    m2 = ndimage.gaussian_filter(lab[..., 0] ** 2, s, mode="nearest")
    spread = np.sqrt(np.maximum(m2 - mean[..., 0] ** 2, 0.0))
    feat = np.concatenate([mean, spread[..., None]], -1)
    out = np.zeros(lab.shape[:2])
    for k, a in enumerate(LINE_ANGLES):
        # the element's direction in the grid, as :func:`_line_footprint` draws it: (-sin, cos)
        dy, dx = int(round(-offset_px * math.sin(a))), int(round(offset_px * math.cos(a)))
        diff = np.sqrt(((_shifted(feat, dy, dx) - _shifted(feat, -dy, -dx)) ** 2).sum(-1))
        out = np.where(across == k, diff, out)
    return out


def frame_evidence(lab: np.ndarray, cfg: "ObserverConfig", lab_bg: np.ndarray | None = None,
                   seg: np.ndarray | None = None) -> np.ndarray:
    """``(h, w)`` d' units: how much stronger the thin dark lines pooled at each place are (:func:`line_map` on L*
    of ``lab`` ``(h, w, 3)``, pooled over the finest centre scale) than the lines of the background around it --
    the object-free view's (``lab_bg``) when given, else the image's own -- on the place's own ground (``seg``),
    in units of their spread over the 4 deg surround (floored at the internal noise): the frame, rails, legs and
    rims of an object, a line drawing's content (Biederman & Ju 1988: objects are recognised from their edges as
    fast as from colour photographs), where the object's surface itself is glass or the ground's colour.

    Only *two-sided* lines count: a line is weighted by how alike its two flanks are (:func:`flank_contrast`,
    perpendicular to the line, just beyond the structuring element's half-length) against the flank contrasts the
    background shows around the place (the same measure on the object-free view, or on the image, across the
    direction: the ground's own texture across a line's width), as a z-score ``z``: full weight for
    ``z <= 1``, none from ``z >= 3`` (linear between). A line with the ground on both sides -- a glass chair's rail
    -- keeps its strength; a line between two different surfaces -- a cast shadow's sliver along its caster, the
    contact line between a box's base and its shadow -- is an edge, not a frame (figure-ground: a line bounded by
    the same region on both sides is a thing, one that separates two regions is their border; Palmer 1999, ch. 6).
    The surround statistics are the same normalised Gaussian means as step 1's; the mask is never read."""
    ppd = cfg.feature_px_per_deg
    length = int(round(FRAME_LINE_DEG * ppd))
    contrast = "ratio" if cfg.frame == "lines_ratio" else "difference"
    li, across = _line_tophats(lab[..., 0], length, contrast)
    ref = lab if lab_bg is None else lab_bg
    lb = li if lab_bg is None else line_map(lab_bg[..., 0], length, contrast)
    sigma_s = cfg.surround_sigma_deg * ppd
    offset = (max(3, length | 1) // 2) + 1  # just beyond the line element's half-length
    fc = flank_contrast(lab, across, offset)
    fb = flank_contrast(ref, across, offset)  # the ground's own, across the same direction at each place
    fmu = _seg_blur(fb, sigma_s, seg)
    fsd = np.sqrt(np.maximum(_seg_blur(fb * fb, sigma_s, seg) - fmu * fmu, 0.0) + cfg.internal_noise ** 2)
    z = (fc - fmu) / fsd
    li = li * np.clip((FLANK_Z_NONE - z) / (FLANK_Z_NONE - FLANK_Z_FULL), 0.0, 1.0)
    # within the flank offset of the image's border a line has one flank in the image: nothing says it is two-sided
    # (read there, both flanks were the border's pixel: flank contrast 0, a "frame" along every border row -- the
    # bottom row of panorama's view 1 took its clicks)
    h, w = li.shape
    yy, xx = np.ogrid[0:h, 0:w]
    li = np.where((np.minimum(yy, h - 1 - yy) < offset) | (np.minimum(xx, w - 1 - xx) < offset), 0.0, li)
    mu = _seg_blur(lb, sigma_s, seg)
    var = np.maximum(_seg_blur(lb * lb, sigma_s, seg) - mu * mu, 0.0)
    return (li - mu) / np.sqrt(var + cfg.internal_noise ** 2)


#: Step 2d's outlined-shadow rule (:func:`evidence_maps`): a line lifts the cast-shadow discount around it only
#: where the cast-shadow map on the line itself is at least this (the line runs on the darkening): half.
CAST_LINE_ON = 0.5
#: ... and only as much as the strongest such line in the foveal window exceeds the ground's own lines (z): none
#: up to 3, in full from 6 (the verification criterion). The maximum over a foveal window of a ground's own line
#: evidence is 2-3 on gravel (about 80 places, each over 2 with p 0.02); the former ramp from 0 to 2 lifted the
#: discount of every cast shadow on gravel (gravel's box view 1: cast map 0.78 -> 0.07 under its base, clicked
#: there). Room's glass chair's lines read 8-10.
OUTLINED_SHADOW_LINE = (3.0, 6.0)
#: :func:`frame_evidence`'s two-sidedness: a line whose flanks differ by at most this z over the ground's own flank
#: contrasts keeps its full strength ...
FLANK_Z_FULL = 4.0
#: ... and from this z on it counts for nothing (an edge between two surfaces).
FLANK_Z_NONE = 8.0


def _scale_maps(lab: np.ndarray, logimg: np.ndarray, sigma_c: float, cfg: ObserverConfig,
                lab_bg: np.ndarray | None = None, log_bg: np.ndarray | None = None,
                seg: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """One centre scale: raw Mahalanobis distances on the full features and on the intensity-invariant ones (log
    chromaticity and the orientation energies of log luminance), the illumination-likeness ``1 - D_inv / D`` in
    [0, 1], the darker-than-surround ramp (widened by the centre's reach) and the shadow-likeness of each place on
    its own (the ramp, not widened, times the illumination-likeness: the mass whose shape :func:`lying_shape`
    reads)."""
    from scipy import ndimage

    ppd = cfg.feature_px_per_deg
    sc = sigma_c * ppd
    f = _features(lab, sc)
    sigma_s = cfg.surround_sigma_deg * ppd
    fb = None if lab_bg is None else _features(lab_bg, sc)
    lfb = None if log_bg is None else _features(log_bg, sc)
    m_full = _mahalanobis(f, sigma_s, _feature_noise(cfg.internal_noise, f.shape[0], cfg.energy_gain), fb, seg)
    lf = _features(logimg, sc)
    m_inv = _shadow_residual(lf, f, sigma_s, cfg.internal_noise, lfb, fb, seg, cfg.energy_gain)
    illum = np.exp(-0.5 * (m_inv / SHADOW_RESIDUAL) ** 2)  # nothing left but what a shadow does
    # as much darker than the surround as a cast shadow is (:data:`SHADOW_FACTOR`), or beside such a place within
    # the centre's reach (the lit side of a shadow's edge, whose pooled features straddle the edge)
    if lfb is not None and cfg.shadow_reference == "background":
        # against the object-free view at this very place (the ratio image): the light the place lost against the
        # same ground unoccluded, on the physical range of a cast shadow (:data:`SHADOW_FACTOR_RATIO`)
        drop = -(lf[0] - lfb[0]) / LOG_UNITS
        lo, hi = -math.log(SHADOW_FACTOR_RATIO[0]), -math.log(SHADOW_FACTOR_RATIO[1])
    else:
        drop = -(lf[0] - _seg_blur(lf[0] if lfb is None else lfb[0], sigma_s, seg)) / LOG_UNITS  # ln(surround/here)
        lo, hi = -math.log(SHADOW_FACTOR[0]), -math.log(SHADOW_FACTOR[1])
    ramp = np.clip((drop - lo) / (hi - lo), 0.0, 1.0)
    darker = ndimage.maximum_filter(ramp, size=2 * int(math.ceil(2 * sc)) + 1, mode="nearest")
    return m_full, m_inv, illum, darker, ramp * illum


def evidence_maps(image: np.ndarray, config: ObserverConfig | None = None,
                  background: np.ndarray | None = None, regional: bool = True,
                  segments: np.ndarray | None = None, normals: np.ndarray | None = None) -> Maps:
    """Steps 1-3 and the verification evidence of step 5 for ``image`` (sRGB ``(H, W, 3)``); see the module
    docstring. With ``saliency_model`` the learned network's z-scored map replaces ``D`` (no shadow analysis).
    ``normals``: the object-free view's world-space surface normals ``(H, W, 3)`` (zeros where no surface is
    seen; :func:`optimizer.rendering.render.surface_normals_views`), which split the grounds into surfaces
    (``ObserverConfig.surfaces``); ignored when ``segments`` is given."""
    cfg = config or ObserverConfig()
    srgb = _as_srgb(image)
    ppd = cfg.feature_px_per_deg
    cast = None  # the cast-shadow texture test's map, where it runs (needs an object-free view)
    zl = None  # step 2d's line evidence, where it runs (frame="lines"; not with a learned saliency model)
    if cfg.saliency_model:
        d = learned_map(srgb, cfg).astype(np.float64)
        d_inv, shadow, obj = d.copy(), np.zeros_like(d), d.copy()
    else:
        scale = cfg.display_deg * ppd / srgb.shape[0]
        small = _resample(srgb, scale)
        lab, logimg = srgb_to_lab(small), _log_image(small)
        lab_bg = log_bg = None
        if background is not None:
            bg = _as_srgb(background)
            if bg.shape != srgb.shape:
                raise CamoError(f"observer: background is {bg.shape[1]}x{bg.shape[0]} but the image is "
                                f"{srgb.shape[1]}x{srgb.shape[0]}")
            small_bg = _resample(bg, scale)
            lab_bg, log_bg = srgb_to_lab(small_bg), _log_image(small_bg)
        sky = sky_map(logimg if log_bg is None else log_bg)
        ground = ~sky
        if segments is None and cfg.surround == "ground":
            if log_bg is not None:
                segments = ground_segments(lab_bg, sky, cfg)  # from the object-free view only
            if normals is not None and cfg.surfaces == "geometry":
                surf = surface_labels(_nearest(_check_normals(normals, srgb.shape), sky.shape))
                segments = combine_segments(segments, surf, sky)
        d = d_inv = shadow = obj = None
        filled = None
        if cfg.frame != "none":  # step 2d: the object's own thin dark lines (a shadow has none)
            zl = _zscore(frame_evidence(lab, cfg, lab_bg, segments), cfg.spread_floor, ground)
        if log_bg is not None and cfg.cast_shadow in ("texture", "texture_chroma"):
            # the ground's own texture, darkened by a shadow's factor: ground in shadow, whatever its outline. Read at
            # the finest centre scale: being shadowed ground is a property of the place, so a coarse scale's features
            # that straddle a body and its attached shadow are discounted where they sit on the shadow only
            cast = cast_shadow_map(logimg, log_bg, cfg.centre_sigmas_deg[0] * ppd, cfg)
            if zl is not None:
                # a darkening outlined or crossed by lines the ground lacks is a surface (Hering's outlined shadow
                # is seen as a stain), not ground in shadow: within the foveal window of such a line, no discount.
                # Only lines that run on the darkening itself (the cast-shadow map at least :data:`CAST_LINE_ON` on
                # the line): an object's own lines beside its attached shadow (a torus's rim) outline the object,
                # not the shadow, and left that shadow undiscounted (occluded's plain tori clicked on it)
                from scipy import ndimage

                win = 2 * int(math.ceil(cfg.verify_sigma_deg * ppd)) + 1
                near = ndimage.maximum_filter(np.where(cast >= CAST_LINE_ON, zl, 0.0), size=win, mode="nearest")
                lo, hi = OUTLINED_SHADOW_LINE
                cast = cast * np.clip((hi - near) / (hi - lo), 0.0, 1.0)
        for sc in cfg.centre_sigmas_deg:
            m_full, m_inv, illum, darker, own = _scale_maps(lab, logimg, sc, cfg, lab_bg, log_bg, segments)
            zf = _zscore(m_full, cfg.spread_floor, ground)
            zi = _zscore(m_inv, cfg.spread_floor, ground)
            shadow_like = darker * illum
            disc = (1.0 if log_bg is not None and cfg.shadow_reference == "background" else cfg.shadow_discount)
            if cfg.shadow_shape == "scales":
                k = shape_over_sizes(own, [size / FWHM * ppd for size in cfg.object_deg])
            elif cfg.shadow_shape == "lying":
                k = lying_shape(own, SHAPE_WINDOW_DEG * ppd)
            if cfg.shadow_shape != "none":
                disc = np.where(k > 0, disc + (1.0 - disc) * k, disc * (1.0 + k))
            if cast is not None:
                discount, shadow_like = np.maximum(disc * shadow_like, cast), np.maximum(shadow_like, cast)
            else:
                discount = disc * shadow_like
            zo = _zscore((1.0 - discount) * m_full, cfg.spread_floor, ground)
            sh = shadow_like * np.maximum(zf, 0.0)
            d, d_inv = (zf, zi) if d is None else (np.maximum(d, zf), np.maximum(d_inv, zi))
            shadow, obj = (sh, zo) if shadow is None else (np.maximum(shadow, sh), np.maximum(obj, zo))
        if zl is not None:  # the lines count in full: a shadow's outline is a step, never a line
            from scipy import ndimage

            d, obj = np.maximum(d, zl), np.maximum(obj, zl)
            # lines closer together than a line's length are one frame: the closing fills what they enclose
            # (grouping by proximity and closure; an isolated line stays a line) -- for the candidate's extent
            # (priority, verification), not for where it is clicked: the lines are the object, the gaps between
            # a chair's legs are not
            n = int(round(FRAME_LINE_DEG * ppd)) | 1
            filled = np.maximum(obj, ndimage.grey_closing(zl, size=(n, n), mode="nearest"))
    if cfg.saliency_model:
        sky = np.zeros(obj.shape, bool)
        filled = None
    bgm = props = None
    if regional and background is not None:
        # the object-free view's own maps: the verification's null below, and the scene's props
        bgm, props = _background_maps(background, cfg, segments)
    def _grounded(o):
        o = np.where(sky, np.minimum(o, 0.0), o)  # no object rests on the sky (ground support)
        if props is not None:  # on a known prop only what the object-free view does not have there counts
            o = np.where(props, o - np.maximum(bgm.obj, 0.0), o)
        return o

    obj = _grounded(obj)
    extent = obj if filled is None else _grounded(filled)  # a frame's lines with what they enclose (step 2d)
    # object-likeness at each expected size: the object evidence pooled over a disc of that size minus the largest
    # pooled evidence on a ring just outside it (a compact thing differs from its surround on every side; an edge
    # or a horizon runs through its own ring)
    sizes = (2 * cfg.verify_sigma_deg * 2,) + tuple(cfg.object_deg)  # a foveal-sized candidate, then the sizes
    compact = [_compactness(extent, size / 2.0 * ppd) for size in sizes]
    verify = np.max(compact, axis=0)
    if regional:
        # the verification's null: the evidence the background alone gives around each place (its regional mean
        # and spread, over the surround); from the object-free view when there is one, else from the image
        # (with shadow_reference "background" the object-free view is its own reference -- nothing in it is darker
        # than itself -- as at the image's places the object leaves unchanged)
        if bgm is None:
            ref = verify
        elif props is None:
            ref = bgm.verify
        else:  # the props are known in the object-free view as well: they do not raise the null around them
            ref = _null_evidence(bgm, props, cfg)
        mu, scale = _regional_null(ref, sky, segments, cfg)
        verify = (verify - mu) / scale
    g = np.max([_zscore(c, 1e-3, ~sky) for c in compact[1:]], axis=0)
    if cfg.shadow_gain > 0 and shadow.max() > 0:
        from scipy import ndimage

        own = _gauss(shadow, cfg.verify_sigma_deg * ppd)
        near = ndimage.maximum_filter(own, size=max(1, int(round(max(cfg.object_deg) * ppd))), mode="nearest")
        g = g + cfg.shadow_gain * np.maximum(near - own, 0.0)  # around the shadow, not on it
    f32 = lambda a: np.asarray(a, np.float32)  # noqa: E731
    return Maps(f32(d), f32(d_inv), f32(shadow), f32(obj), f32(g), f32(verify), sky,
                None if cast is None else f32(cast), None if zl is None else f32(np.where(sky, 0.0, zl)))


#: How many object-free views' own maps :func:`_background_maps` keeps (least recently used dropped first).
BACKGROUND_CACHE_SIZE = 8
_BACKGROUND_CACHE: dict[str, tuple[Maps, np.ndarray | None]] = {}


def _background_maps(background: np.ndarray, cfg: ObserverConfig,
                     segments: np.ndarray | None) -> tuple[Maps, np.ndarray | None]:
    """The object-free view's own maps (the verification's null) and its scene props, for :func:`evidence_maps`.

    They depend on the object-free view, the configuration and the ground segments only, not on the image, so the
    last :data:`BACKGROUND_CACHE_SIZE` are kept by content hash: one background is shown with several objects or
    methods (the property tests' synthetic grounds; a view's background against every method's stimulus), and its
    maps are half of :func:`evidence_maps`' time (a 256-px stimulus at 16 px/deg, 300 trials: 6.0 CPU s for a
    prediction without the cache, 3.3 with it). The cached arrays are read-only, so a caller cannot change a later
    caller's null."""
    import hashlib

    h = hashlib.blake2b(repr(cfg).encode(), digest_size=16)  # (evaluation.turntable's hash would be an import cycle)
    for a in (background, segments):
        a = np.zeros(0, bool) if a is None else np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    key = h.hexdigest()
    hit = _BACKGROUND_CACHE.pop(key, None)
    if hit is None:
        same = background if cfg.shadow_reference == "background" else None
        bgm = evidence_maps(background, cfg, same, regional=False, segments=segments)
        props = scene_props(bgm, cfg, segments) if cfg.props == "scene" and not cfg.saliency_model else None
        for a in [*(getattr(bgm, f.name) for f in dataclasses.fields(bgm)), props]:
            if isinstance(a, np.ndarray):
                a.setflags(write=False)
        hit = (bgm, props)
    _BACKGROUND_CACHE[key] = hit  # re-inserted last: the most recently used
    while len(_BACKGROUND_CACHE) > BACKGROUND_CACHE_SIZE:
        del _BACKGROUND_CACHE[next(iter(_BACKGROUND_CACHE))]
    return hit


#: Object evidence (d', z over the ground) from which a place of the object-free view connected to a prop's
#: compact core belongs to the same prop (:func:`scene_props`): 2, the 98th percentile of a normal ground.
PROP_EVIDENCE = 2.0


def _null_evidence(bg_maps: Maps, props: np.ndarray, cfg: ObserverConfig) -> np.ndarray:
    """The verification's null evidence of the object-free view: its compactness (step 5, max over the candidate
    sizes) with the sky and the known ``props`` taken out (they do not raise the bar around them)."""
    ppd = cfg.feature_px_per_deg
    sizes = (2 * cfg.verify_sigma_deg * 2,) + tuple(cfg.object_deg)
    ob_ = np.where(bg_maps.sky | props, np.minimum(bg_maps.obj, 0.0), bg_maps.obj)
    return np.max([_compactness(ob_, size / 2.0 * ppd) for size in sizes], axis=0)


def _regional_null(ref: np.ndarray, sky: np.ndarray, segments: np.ndarray | None,
                   cfg: ObserverConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(mu, scale)``: the mean of the null evidence ``ref`` over the 4 deg surround on the place's own ground and
    its spread there, at least the ground's overall robust spread (step 5's regional z is ``(V - mu) / scale``)."""
    sig = cfg.surround_sigma_deg * cfg.feature_px_per_deg
    mu = _seg_blur(ref, sig, segments)
    sd = np.sqrt(np.maximum(_seg_blur(ref * ref, sig, segments) - mu * mu, 0.0))
    ground = ~sky
    v = ref[ground] if ground.any() else ref.ravel()
    floor = max(1.4826 * float(np.median(np.abs(v - np.median(v)))), 1e-3)
    return mu, np.maximum(sd, floor)


#: Most rounds of :func:`scene_props`'s self-verification (each adds the object-free view's places that pass
#: verification once the props found so far no longer raise the null; it stops earlier when a round adds none).
PROP_ROUNDS = 4


def scene_props(bg_maps: Maps, config: ObserverConfig | None = None,
                segments: np.ndarray | None = None) -> np.ndarray:
    """``(h, w)`` bool: the places of the *object-free* view (its :class:`Maps`, computed with ``regional=False``)
    that belong to a prop of the scene (``ObserverConfig.props``).

    A prop's core is a place of the object-free view that stands out from its ground as compactly as a target
    must to be verified: its priority (object-sized compactness, z over the ground, step 3) at least the
    verification ``criterion``, and (``prop_test="verify"``, the default) any place that the verification itself
    (step 5: the regional z against the object-free view's own null, ``segments`` its grounds) would accept there
    once the props found so far no longer raise that null -- repeated until a round adds no place (at most
    :data:`PROP_ROUNDS`). The priority is z-scored over the whole ground, the verification against the place's own
    4 deg surround, so a large flat thing on an even floor (room's grey box: priority 5.1 in its object-free view)
    can pass the second without the first; whatever the observer would click as the object in the scene without
    the object is, by construction, part of the scene. The rest of the same thing -- a wall's middle, whose ring is the wall itself, a
    crate's faces -- is the connected region of object evidence at least :data:`PROP_EVIDENCE` that holds a core
    (hysteresis linking, Canny 1986, IEEE PAMI 8). Ground texture rarely forms a core: on the six built-in scenes'
    object-free views cores lie on occluded's crate and walls, panorama's pillar and block (and their shadows),
    room's ceiling light and a wall's edge, and, from the grounds alone, on one grass patch (meadow view 1), the
    horizon under the sun's glow (gravel view 1) and the border of split's two grounds (view 1) -- those places too
    then count only by what the object-free view lacks there."""
    from scipy import ndimage

    cfg = config or ObserverConfig()
    ground = ~bg_maps.sky
    lab, _ = ndimage.label((bg_maps.obj >= PROP_EVIDENCE) & ground)

    def grown(core: np.ndarray) -> np.ndarray:
        keep = np.unique(lab[core])
        return core | np.isin(lab, keep[keep > 0])

    bar = cfg.criterion - cfg.prop_margin * cfg.verify_noise  # what the noisy verification may accept
    props = grown((bg_maps.guidance >= bar) & ground)
    if cfg.prop_test == "verify":
        for _ in range(PROP_ROUNDS):
            ref = _null_evidence(bg_maps, props, cfg)
            mu, scale = _regional_null(ref, bg_maps.sky, segments, cfg)
            new = ((ref - mu) / scale >= bar) & ground & ~props
            if not new.any():
                break
            props = props | grown(new)
    return props


#: Pooling of the features that tell one ground from another (Gaussian sigma, degrees): half a degree, a third of
#: the smallest object the study shows -- the scale of a ground's texture, not of its grain.
SEGMENT_SIGMA_DEG = 0.5
#: Two grounds are told apart when their colour distributions are separated by at least this d' (Fisher's
#: discriminant: the distance of the k-means clusters' means in units of the pooled within-cluster spread): 5.
#: One ground whose colour drifts across the frame (distance, light falloff) splits into two clusters too, at
#: d' = sqrt(12) = 3.5 for an even drift (a uniform distribution) and 2.6 for a normal one; two normal
#: distributions 5 apart overlap by 1 %. Each ground must cover at least :data:`SEGMENT_MIN_SHARE` of the frame
#: (a patch smaller than the largest object the study shows is no ground).
SEGMENT_SEPARATION = 5.0
SEGMENT_MIN_SHARE = 0.05
#: Most grounds told apart besides the sky (k-means with k = 3, 2, 1: the largest whose grounds all pass).
SEGMENT_MAX = 3


def ground_segments(lab: np.ndarray, sky: np.ndarray, config: ObserverConfig | None = None) -> np.ndarray:
    """``(h, w)`` int labels of the grounds of an *object-free* view (``lab``: its CIE L*a*b* ``(h, w, 3)`` at the
    feature resolution, ``sky``: :func:`sky_map`): 0 .. K-1 for up to :data:`SEGMENT_MAX` grounds, K for the sky
    when there is one; all 0 when the view has one ground and no sky.

    A place's surround statistics are taken on its own ground (``ObserverConfig.surround="ground"``): a person
    searching split's marble-and-asphalt floor compares a place on the asphalt with asphalt, not with the mixture
    of both that a pooled 4 deg surround gives at their border (Rosenholtz et al. 2007's target-vs-surround
    statistics presuppose a homogeneous surround; figure-ground and region segmentation precede search in
    scene perception: Wolfe, Vo, Evans & Greene 2011, TICS 15, "Visual search in scenes involves selective and
    nonselective pathways"). The grounds are k-means clusters (SciPy, seeded: deterministic) of the colour of
    step 1 (L*a*b*; not the texture energies, which change with distance on one ground) pooled at
    :data:`SEGMENT_SIGMA_DEG`, on the places that are not sky; k is the largest (of 3, 2, 1) whose clusters are
    pairwise separated by :data:`SEGMENT_SEPARATION` (Fisher's d') and each cover :data:`SEGMENT_MIN_SHARE` of the
    frame. Labels are cleaned by a majority vote over the same pooling. Read from the object-free render only, so
    they never say where the object is (the object's place gets the label of the ground behind it)."""
    from scipy import ndimage
    from scipy.cluster.vq import kmeans2

    cfg = config or ObserverConfig()
    ppd = cfg.feature_px_per_deg
    sg = SEGMENT_SIGMA_DEG * ppd
    f = _features(lab, sg)[:3]  # (3, h, w): colour only (a ground's texture coarsens with distance, its colour not)
    h, w = sky.shape
    ground = ~sky
    labels = np.zeros((h, w), int)
    x = f[:, ground].T
    if x.shape[0] >= 16:
        mu, sd = x.mean(0), x.std(0) + 1e-6
        z = (x - mu) / sd
        for k in range(SEGMENT_MAX, 1, -1):
            cent, lab_k = kmeans2(z, k, minit="++", seed=0)
            counts = np.bincount(lab_k, minlength=k)
            if counts.min() < SEGMENT_MIN_SHARE * h * w:
                continue
            within = sum(np.cov(z[lab_k == j].T) * (counts[j] - 1) for j in range(k)) / max(len(z) - k, 1)
            within = within + 1e-6 * np.eye(within.shape[0])
            sep = min(float(np.sqrt((cent[i] - cent[j]) @ np.linalg.solve(within, cent[i] - cent[j])))
                      for i in range(k) for j in range(i + 1, k))
            if sep < SEGMENT_SEPARATION:
                continue
            full = np.full((h, w), -1)
            full[ground] = lab_k
            votes = np.stack([ndimage.gaussian_filter((full == j).astype(np.float64), sg, mode="nearest")
                              for j in range(k)])
            labels = np.where(ground, votes.argmax(0), 0)
            break
    if sky.any():
        labels = np.where(sky, labels.max() + 1, labels)
    return labels


#: Two places of the object-free view are on one surface when their normals are less than this angle apart
#: (:func:`surface_labels`): 45 deg, halfway between parallel and perpendicular, so a floor and a wall (90 deg
#: apart) split at their bisector while a terrain's slopes (under 45 deg on the built-in outdoor scenes) stay one
#: ground with its floor.
SURFACE_ANGLE_DEG = 45.0
#: Most surfaces told apart in one view (orientation groups; a room seen from inside shows at most a floor, a
#: ceiling and three walls; smaller groups join the nearest one).
SURFACE_MAX = 6


def _check_normals(normals: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    n = np.asarray(normals, np.float64)
    if n.ndim != 3 or n.shape[2] != 3 or n.shape[:2] != tuple(shape[:2]):
        raise CamoError(f"observer: normals are {'x'.join(map(str, n.shape))} but the image is "
                        f"{shape[1]}x{shape[0]} (need H x W x 3)")
    return n


def _nearest(a: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``a`` ``(H, W, ...)`` sampled at the centres of an ``(h, w)`` grid over the same frame (nearest pixel): a
    normal or a label is not averaged across a surface's edge."""
    H, W = a.shape[:2]
    h, w = shape
    r = np.minimum(((np.arange(h) + 0.5) * H / h).astype(int), H - 1)
    c = np.minimum(((np.arange(w) + 0.5) * W / w).astype(int), W - 1)
    return a[r][:, c]


def surface_labels(normals: np.ndarray) -> np.ndarray:
    """``(h, w)`` int labels of the surfaces of an *object-free* view from its world-space normals ``(h, w, 3)``
    (zeros where no surface is seen: label -1): 0 .. K-1 for up to :data:`SURFACE_MAX` orientation groups.

    Mode seeking on the sphere of directions: the group's direction is the normal with the most places within
    :data:`SURFACE_ANGLE_DEG` of it (candidates: a regular subsample), refined as the mean normal of its members
    (three rounds); its members leave and the next group is sought, while a group holds at least
    :data:`SEGMENT_MIN_SHARE` of the frame (a smaller patch is no ground). Places left over join the group whose
    direction is nearest. Weight-free: the angle is half a right angle; no position or colour is read, so a
    floor, the walls and a ceiling of one material are told apart exactly where a person sees them meet
    (Gibson 1950, *The Perception of the Visual World*: surfaces and their layout, not colours, are what a
    scene's ground is made of)."""
    n = np.asarray(normals, np.float64)
    h, w = n.shape[:2]
    flat = n.reshape(-1, 3)
    seen = np.linalg.norm(flat, axis=1) > 0.5
    labels = np.full(h * w, -1, int)
    if not seen.any():
        return labels.reshape(h, w)
    flat = flat / np.maximum(np.linalg.norm(flat, axis=1, keepdims=True), 1e-12)
    cos = math.cos(math.radians(SURFACE_ANGLE_DEG))
    bar = SEGMENT_MIN_SHARE * h * w
    remaining = seen.copy()
    modes: list[np.ndarray] = []
    while len(modes) < SURFACE_MAX and remaining.sum() >= bar:
        idx = np.flatnonzero(remaining)
        cand = flat[idx[:: max(1, idx.size // 256)]]
        votes = flat[idx[:: max(1, idx.size // 4096)]]
        mode = cand[int(np.argmax((votes @ cand.T >= cos).sum(0)))]
        for _ in range(3):
            members = remaining & (flat @ mode >= cos)
            m = flat[members].sum(0)
            mode = m / max(float(np.linalg.norm(m)), 1e-12)
        members = remaining & (flat @ mode >= cos)
        if members.sum() < bar:
            break
        labels[members] = len(modes)
        remaining &= ~members
        modes.append(mode)
    left = seen & (labels < 0)
    if modes and left.any():
        labels[left] = np.argmax(flat[left] @ np.stack(modes).T, axis=1)
    return labels.reshape(h, w)


def combine_segments(grounds: np.ndarray | None, surfaces: np.ndarray, sky: np.ndarray) -> np.ndarray:
    """The grounds a place's surround is taken on (``surround="ground"``) with surfaces: each colour ground of
    :func:`ground_segments` (``grounds``; None = one ground) split by the :func:`surface_labels` ``surfaces``
    it lies on (-1, no surface: a group of its own); the sky stays one label, the last (as in
    :func:`ground_segments`). A part smaller than :data:`SEGMENT_MIN_SHARE` of the frame joins the largest part of
    the same surface (else of the same colour ground): too few places for a surround's statistics."""
    h, w = sky.shape
    g = np.zeros((h, w), int) if grounds is None else np.asarray(grounds, int)
    ground = ~sky
    ns = int(surfaces.max()) + 2
    pair = np.where(ground, g * ns + (surfaces + 1), -1)
    keys, counts = np.unique(pair[ground], return_counts=True)
    bar = SEGMENT_MIN_SHARE * h * w
    big = {int(k) for k, c in zip(keys, counts) if c >= bar}
    size = dict(zip(keys.tolist(), counts.tolist()))
    for k in keys.tolist():
        if k in big:
            continue
        same_surf = [b for b in big if b % ns == k % ns]
        same_ground = [b for b in big if b // ns == k // ns]
        into = max(same_surf or same_ground or [k], key=lambda b: size[b])
        pair[pair == k] = into
    out = np.zeros((h, w), int)
    for i, k in enumerate(np.unique(pair[ground]).tolist()):
        out[pair == k] = i
    if sky.any():
        out[sky] = out[ground].max() + 1 if ground.any() else 0
    return out


#: Window of the shape cue with ``shadow_shape="lying"`` (Gaussian sigma, degrees): the region read around a place
#: spans ~2.4 deg (its FWHM), the middle of the object sizes the study shows (1.6-4.8 deg) -- about a cast shadow's
#: length and an object's height. The default ``"scales"`` reads one window per object size (:func:`shape_over_sizes`).
SHAPE_WINDOW_DEG = 1.0
#: Shape score (:func:`lying_shape`) from which a shadow-like region counts fully as lying (or, negated, as
#: upright): 0.3, the elongation ``(a^2 - 1) / (a^2 + 1)`` of a region 1.4 times as long as it is thick -- a
#: daylight shadow of an upright object is 2-5 times longer than thick (sun elevations of 20-60 deg), and ground
#: foreshortening at the built-in scenes' camera elevations (10-40 deg) flattens a round patch 1.5-6-fold.
SHAPE_FULL = 0.3
#: An *upright* reading needs a region bounded on both sides across its short axis within the window (an object
#: is; the straight edge of a shade larger than the window is not): the upright score counts fully while the
#: region's minor-axis variance ``l2`` is below the first share of the window's ``sigma^2`` and fades linearly to
#: 0 at the second, the ``l2`` of a half-plane, ``(1 - 2 / pi) sigma^2 = 0.36 sigma^2`` -- so the edge of a large
#: shade keeps ``shadow_discount`` (without this, split's boundary between its dark and light ground read as an
#: upright thing and its vase beside it went unverified). An object up to ~1.5 deg across (``l2 <= 0.2
#: sigma^2``) counts fully. A lying reading needs no bound: a broad shade lying on the ground is shadow as well.
SHAPE_THIN = (0.2, 0.36)


def lying_shape(mass: np.ndarray, sigma: float) -> np.ndarray:
    """Signed shape score in [-1, 1] of the region ``mass`` ``(h, w)`` (>= 0) around every place: +1 lying on the
    ground, -1 upright, 0 round or unbounded within the window (Gaussian, ``sigma`` px).

    The second moments of the mass around its local centroid (``C_xx``, ``C_yy``, ``C_xy``, computed with
    separable moment kernels ``x^k g(x)``) give the region's elongation ``e = (l1 - l2) / (l1 + l2)`` and the
    angle of its long axis. ``upright = max(0, (C_yy - C_xx) / (C_xx + C_yy))`` -- taller than wide, i.e.
    ``e cos(2 phi)`` for a long axis within 45 deg of the vertical; ``lying = e - upright``: elongated off the
    vertical, or wider than tall. The score is ``(lying - upright) /`` :data:`SHAPE_FULL`, clipped; a negative
    (upright) score is scaled by how bounded the region is across its short axis (:data:`SHAPE_THIN`: the
    straight edge of a large shade is no upright thing).

    Why shape tells a cast shadow from an object where photometry cannot (a shadow keeps 23-47 % of the light, an
    object's face turned from the sun 36 %, with the same chromaticity shift: docs/results/observer.md): a cast
    shadow lies on the ground plane, so perspective flattens it vertically by the sine of the viewing elevation
    (Gibson 1950's texture gradient; slant from foreshortening, Stevens 1981, Artif. Intell. 17), and it is
    stretched along the light's direction away from its caster (Mamassian, Knill & Kersten 1998, TICS 2, "The
    perception of cast shadows": a shadow is read as a flat dark region attached to the object, on the surface
    that receives it); an object stands up from the ground -- people search for objects on their supporting
    surface (Biederman et al. 1982) and take a dark region attached to an upright thing's base for its shadow,
    not for the thing. Objects in the study are upright solids (the silhouette class of the practice trials:
    vases, boxes, bottles) whose image outline is at least as tall as wide.

    The image's frame is not the region's outline: the mass at the frame is continued beyond it (each border
    pixel's value outward), so a region the frame cuts reads as going on across the frame, and a region that does
    not reach the frame reads as before. With zeros outside (the former rule) the stub of a lying cast shadow
    running out of the side of the frame -- taller than wide in the frame -- read fully upright (-1 at every
    window and centre scale), kept all its object evidence and drew every click: panorama's Ours view 1, the box's
    shadow at the right edge (object evidence 7.0 there against at most 4.6 on the box), and occluded's
    Transparent view 3, a wedge's shadow at the left edge (docs/results/observer.md). Mirroring instead (as
    :func:`_features` does) also fixed those two but put a mirrored copy of a shadow that ends near the frame
    beyond it (meadow's Ours view 3: 10 % of the clicks on its long shadow's tail, 14 px above the frame)."""
    from scipy import ndimage

    r = int(math.ceil(3 * sigma))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k0 = np.exp(-x * x / (2 * sigma * sigma))
    k1, k2 = x * k0, x * x * k0

    def conv(kr: np.ndarray, kc: np.ndarray) -> np.ndarray:  # the frame is no outline: continued beyond it
        return ndimage.correlate1d(ndimage.correlate1d(mass, kr, axis=0, mode="nearest"), kc, axis=1,
                                   mode="nearest")

    m0 = conv(k0, k0) + 1e-9
    mx, my = conv(k0, k1) / m0, conv(k1, k0) / m0
    cxx = conv(k0, k2) / m0 - mx * mx
    cyy = conv(k2, k0) / m0 - my * my
    cxy = conv(k1, k1) / m0 - mx * my
    tr = np.maximum(cxx + cyy, 1e-9)
    sq = np.sqrt((cxx - cyy) ** 2 + 4.0 * cxy * cxy)
    e = sq / tr
    upright = np.maximum((cyy - cxx) / tr, 0.0)
    l2 = 0.5 * (tr - sq) / (sigma * sigma)  # minor-axis variance, in units of the window's sigma^2
    thin = np.clip((SHAPE_THIN[1] - l2) / (SHAPE_THIN[1] - SHAPE_THIN[0]), 0.0, 1.0)
    score = np.clip((e - 2.0 * upright) / SHAPE_FULL, -1.0, 1.0)
    return np.where(score < 0.0, score * thin, score)  # upright: only a region bounded on both sides


#: Full width at half maximum of a Gaussian in units of its sigma (2 sqrt(2 ln 2)): a shape window whose FWHM is an
#: object size the study shows.
FWHM = 2.0 * math.sqrt(2.0 * math.log(2.0))


def shape_over_sizes(mass: np.ndarray, sigmas: Sequence[float]) -> np.ndarray:
    """:func:`lying_shape` read with one window per object size the participant expects (``sigmas``, px: the
    sizes of ``ObserverConfig.object_deg`` as the windows' FWHM, 0.68 / 1.36 / 2.04 deg for 1.6 / 3.2 / 4.8 deg),
    keeping per place the most decisive reading (the largest ``|score|``).

    One 1 deg window (:data:`SHAPE_WINDOW_DEG`) reads a region only up to ~2.4 deg across: inside a larger one --
    gravel's glass box, 3.1 x 4.6 deg, whose rendered glass keeps 55 % of the light with a shadow's blue shift --
    the window is filled and reads neither way, so the object kept ``shadow_discount`` and went unverified. Read at
    the object's own size it is the upright thing it is. The scale is chosen per place where the reading is
    strongest: automatic scale selection by the maximum over scales of a normalised response (Lindeberg 1998,
    Int. J. Comput. Vision 30, "Feature detection with automatic scale selection"); the score is already
    normalised (a ratio of second moments in [-1, 1]), so it needs no scale factor. A lying shadow stays lying at
    every window; a shade larger than every window keeps ``shadow_discount`` as before."""
    ks = np.stack([lying_shape(mass, s) for s in sigmas])
    return np.take_along_axis(ks, np.abs(ks).argmax(0)[None], 0)[0]


#: Largest change of log luminance or log chromaticity (``LOG_UNITS`` units) between neighbouring feature pixels
#: (0.1 deg) in a place counted as *smooth* (sky): one internal-noise unit, a contrast step of ~4.6 % -- the Weber
#: fraction; a clear or overcast sky's gradient is about a tenth of it, any textured ground far more.
SKY_STEP = 2.3


def sky_map(logimg: np.ndarray) -> np.ndarray:
    """``(h, w)`` bool: the sky of a scene image -- the smooth region (no step above :data:`SKY_STEP` in log
    luminance or log chromaticity, :func:`_log_image` ``(h, w, 3)``) connected to the top border and not to the
    bottom one, with what it encloses (the sun's disc, a bird, a cloud edge: things not resting on the ground).

    The observer's object prior: objects rest on a support (Biederman, Mezzanotte & Rabinowitz 1982, Cogn.
    Psychol. 14: a floating object is a violation people notice), and people searching a scene for an object look
    at the surfaces that can carry it, not at the sky (Neider & Zelinsky 2006, Vision Res. 46, "Scene context
    guides eye movements during visual search": searching for a jeep, fixations on the sky were almost nil;
    Torralba, Oliva, Castelhano & Henderson 2006, Psychol. Rev. 113: contextual guidance by the scene's
    horizontal layout). A sky's glow, sun or gradient is therefore no candidate. A top-down view with ground up to
    the top border has no smooth region there and no sky."""
    from scipy import ndimage

    step = np.zeros(logimg.shape[:2], bool)
    for k in range(logimg.shape[2]):
        c = logimg[..., k]
        step[:, 1:] |= np.abs(np.diff(c, axis=1)) > SKY_STEP
        step[:, :-1] |= np.abs(np.diff(c, axis=1)) > SKY_STEP
        step[1:] |= np.abs(np.diff(c, axis=0)) > SKY_STEP
        step[:-1] |= np.abs(np.diff(c, axis=0)) > SKY_STEP
    lab, _ = ndimage.label(~step)
    top, bottom = set(np.unique(lab[0])) - {0}, set(np.unique(lab[-1])) - {0}
    keep = sorted(top - bottom)
    sky = np.isin(lab, keep) if keep else np.zeros(step.shape, bool)
    if not sky.any() or sky.mean() < 0.02:  # a few smooth pixels at the top are no sky
        return np.zeros(step.shape, bool)
    # what the sky encloses: holes, and the step pixels along its border (closing by one pixel)
    sky = ndimage.binary_closing(sky, iterations=1, border_value=1) | sky
    return ndimage.binary_fill_holes(sky)


def _disc(r: float) -> np.ndarray:
    rr = int(math.ceil(r))
    yy, xx = np.mgrid[-rr:rr + 1, -rr:rr + 1]
    return (yy ** 2 + xx ** 2) <= r * r


#: Sectors of the ring around a candidate disc (every 45 deg) and the distance of their centres (disc radii).
RING_SECTORS = 8
RING_DISTANCE = 2.5


def _compactness(obj: np.ndarray, radius: float) -> np.ndarray:
    """How much a disc of ``radius`` px stands out as a whole: the mean object evidence over the disc minus the
    **second largest** mean over :data:`RING_SECTORS` discs of the same size whose centres lie
    :data:`RING_DISTANCE` radii away (the ring just outside it). A compact thing differs from its surround on
    every side but the one where it may touch its own shadow or another thing; an edge, a horizon or a shadow's
    border runs through two opposite sectors and so is not compact. Computed on a grid ``radius / 4`` times
    coarser for large discs (the disc means are smooth at that scale)."""
    from scipy import ndimage

    q = max(1, int(radius // 4))
    h, w = obj.shape
    small = obj if q == 1 else ndimage.zoom(_gauss(obj, 0.5 * q), 1.0 / q, order=1, mode="nearest", grid_mode=True)
    r = radius / q
    k = _disc(r).astype(np.float64)
    mean = ndimage.convolve(small, k, mode="constant") / np.maximum(
        ndimage.convolve(np.ones_like(small), k, mode="constant"), 1e-9)  # only pixels inside the image
    sh, sw = mean.shape
    typical = float(np.median(mean))
    pad = int(math.ceil(RING_DISTANCE * r)) + 1
    big = np.pad(mean, pad, mode="constant", constant_values=np.nan)
    sectors = []
    for j in range(RING_SECTORS):
        th = 2 * math.pi * j / RING_SECTORS
        dy, dx = int(round(RING_DISTANCE * r * math.sin(th))), int(round(RING_DISTANCE * r * math.cos(th)))
        sectors.append(big[pad + dy:pad + dy + sh, pad + dx:pad + dx + sw])
    sec = np.stack(sectors)
    half = RING_SECTORS // 2
    opposite = sec[np.r_[half:RING_SECTORS, 0:half]]
    # a sector outside the image: the opposite one's (a line that meets the border goes on beyond it), or the
    # image's typical disc when both are outside
    sec = np.where(np.isnan(sec), opposite, sec)
    sec = np.where(np.isnan(sec), typical, sec)
    second = np.sort(sec, axis=0)[-2]
    out = mean - second
    if q > 1:
        out = ndimage.zoom(out, (h / out.shape[0], w / out.shape[1]), order=1, mode="nearest", grid_mode=True)
    return out[:h, :w]


def discriminability_map(image: np.ndarray, config: ObserverConfig | None = None) -> np.ndarray:
    """The observer's discriminability ``D`` (step 1, d' units, float32, ``(h, w)``); with ``saliency_model`` the
    learned network's map (:func:`learned_map`)."""
    return evidence_maps(image, config).d


@dataclass
class Cells:
    """The search grid of one image: per cell its priority, the verification evidence of a fixation on it, where
    that fixation's click lands, in degrees and in image pixels. Arrays have ``C`` rows (one per cell)."""

    g: np.ndarray  # (C,) priority G at the cell (max over its feature pixels), d'
    v: np.ndarray  # (C,) verification evidence of a fixation on the cell (max within verify_radius_deg), d'
    pos_deg: np.ndarray  # (C, 2) cell centre (x, y) in degrees from the image's top-left corner
    click_px: np.ndarray  # (C, 2) int: (x, y) image pixel clicked when the fixation on this cell verifies
    width_deg: float
    height_deg: float
    image_shape: tuple[int, int]

    @property
    def d(self) -> np.ndarray:  # the verification evidence (kept under its old name for callers)
        return self.v


def make_cells(image: np.ndarray, config: ObserverConfig | None = None, maps: Maps | None = None,
               background: np.ndarray | None = None, normals: np.ndarray | None = None) -> Cells:
    """The search grid of ``image`` (sRGB ``(H, W, 3)``): cells of ``cell_deg``; per cell the priority (max of
    ``G`` in the cell), the verification evidence (max of the foveal evidence within ``verify_radius_deg`` of the
    cell centre) and the image pixel of that maximum (the click). ``background``, ``normals``: the object-free
    view and its surface normals (:func:`evidence_maps`)."""
    from scipy import ndimage

    cfg = config or ObserverConfig()
    srgb = _as_srgb(image)
    H, W = srgb.shape[:2]
    maps = maps if maps is not None else evidence_maps(srgb, cfg, background, normals=normals)
    h, w = maps.guidance.shape
    ppd = cfg.feature_px_per_deg
    n = max(1, int(round(cfg.cell_deg * ppd)))
    ch, cw = math.ceil(h / n), math.ceil(w / n)
    pad = np.full((ch * n, cw * n), -np.inf, np.float32)
    pad[:h, :w] = maps.guidance
    g = pad.reshape(ch, n, cw, n).max(axis=(1, 3))
    # verification: the largest foveal evidence within the window around each cell centre, and where it is
    r = cfg.verify_radius_deg * ppd
    rr = int(math.ceil(r))
    yy, xx = np.mgrid[-rr:rr + 1, -rr:rr + 1]
    foot = (yy ** 2 + xx ** 2) <= r * r
    vmax = ndimage.maximum_filter(maps.verify, footprint=foot, mode="constant", cval=-np.inf)
    iy, ix = np.mgrid[0:ch, 0:cw]
    cy = np.minimum(((iy + 0.5) * n).astype(int), h - 1)
    cx = np.minimum(((ix + 0.5) * n).astype(int), w - 1)
    v = vmax[cy, cx]
    # the argmax inside each window (ties: the first in raster order, deterministic)
    py, px = np.empty_like(cy), np.empty_like(cx)
    for k, (y0, x0) in enumerate(zip(cy.ravel(), cx.ravel())):
        ys, xs = slice(max(0, y0 - rr), min(h, y0 + rr + 1)), slice(max(0, x0 - rr), min(w, x0 + rr + 1))
        win = np.where(foot[ys.start - y0 + rr:ys.stop - y0 + rr, xs.start - x0 + rr:xs.stop - x0 + rr],
                       maps.verify[ys, xs], -np.inf)
        a = int(np.argmax(win))
        py.flat[k], px.flat[k] = ys.start + a // win.shape[1], xs.start + a % win.shape[1]
    # the click: from the window's best place up the evidence to its local peak (the candidate's centre, not the
    # edge of the window nearest to it)
    py, px = _climb(maps.verify, py.ravel(), px.ravel())
    if cfg.click in ("body", "thing", "core"):
        body = _gauss(maps.obj.astype(np.float64), cfg.verify_sigma_deg * ppd)
        py, px = _climb(body, py, px)
        if cfg.click == "thing":
            # where the body's peak looks more like a shadow than like the object (its shadow evidence larger than
            # its object evidence, both pooled at the foveal scale: an object's shaded side meeting its own cast
            # shadow), on to where the object evidence most exceeds the shadow evidence -- but only onto the same
            # thing: where the object evidence is still at least half the peak's (:data:`CLICK_HALF_PEAK`). A dark
            # object is as shadow-like in colour as it is object-like all over (split's dark vases): left at the
            # body's peak, as the climb would take it to its outline
            shade = _gauss(maps.shadow.astype(np.float64), cfg.verify_sigma_deg * ppd)
            qy, qx = _climb(body - shade, py, px)
            same = (shade[py, px] > body[py, px]) & (body[qy, qx] >= CLICK_HALF_PEAK * body[py, px])
            if maps.cast is not None:
                # and only where the peak is the ground in a cast shadow by the texture test (the object-free
                # view's own texture, darkened): a dark or glass object is shadow-like in colour all over but shows
                # no ground texture, and climbing O - S D from it leaves it for the blur of its own evidence
                # outside its outline (split's grey vase, panorama's glass box: 100 % missed)
                same &= maps.cast[py, px] >= CLICK_CAST_SHADOW
            py, px = np.where(same, qy, py), np.where(same, qx, px)
        if cfg.click == "core":
            py, px = core_click(body, py, px, max(cfg.object_deg) / 2.0 * ppd)
        if cfg.frame != "none" and maps.lines is not None:
            # a frame's pooled evidence peaks between its lines (under a chair's seat, between its legs), where
            # nothing of the object is: where a line of the frame within the fovea's pooling radius is stronger than
            # the object evidence at the click, the click goes on to the strongest such line. Only the two-sided
            # lines (:func:`frame_evidence`) draw it, and only off a weaker place: a plain object's body is stronger
            # than any line beside it, so its click stays on it (the former rule -- on to the strongest object
            # evidence of any kind -- took plain objects' clicks onto their attached shadows' edges, 1-6 px out)
            r = max(1, int(round(cfg.verify_sigma_deg * ppd)))
            o, ln = maps.obj.astype(np.float64), maps.lines.astype(np.float64)
            fy, fx = py.copy(), px.copy()
            best = o[py, px].copy()
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    if dy * dy + dx * dx > r * r:
                        continue
                    qy, qx = np.clip(py + dy, 0, h - 1), np.clip(px + dx, 0, w - 1)
                    better = ln[qy, qx] > best
                    best = np.where(better, ln[qy, qx], best)
                    fy, fx = np.where(better, qy, fy), np.where(better, qx, fx)
            py, px = fy, fx
    py, px = py.reshape(cy.shape), px.reshape(cx.shape)
    sy, sx = H / h, W / w
    click = np.stack([np.clip(((px + 0.5) * sx).astype(int), 0, W - 1),
                      np.clip(((py + 0.5) * sy).astype(int), 0, H - 1)], -1)
    pos = np.stack([(cx + 0.5) / ppd, (cy + 0.5) / ppd], -1)
    return Cells(g.reshape(-1).astype(np.float64), v.reshape(-1).astype(np.float64), pos.reshape(-1, 2),
                 click.reshape(-1, 2), w / ppd, h / ppd, (H, W))


#: Object evidence (d', z over the ground) from which a place connected to the verified peak belongs to the thing
#: that was identified (:func:`core_click`): the extent rule of the scene's props (:data:`PROP_EVIDENCE`).
CLICK_EVIDENCE = PROP_EVIDENCE
#: A place of that thing is in its *core* when it lies at least this share of the thing's largest depth (distance to
#: its outline) inside it: half, so the click keeps half the thing's half-width from its outline.
CLICK_CORE_DEPTH = 0.5
#: ``click="thing"``: a place belongs to the thing whose object evidence peaks at the body's peak while its evidence
#: is at least this share of the peak's -- half, the half-maximum extent by which a blob's size is read (its FWHM).
CLICK_HALF_PEAK = 0.5
#: ``click="thing"`` with an object-free view: the body's peak is left only where the cast-shadow map
#: (:func:`cast_shadow_map`, [0, 1]) there is at least this -- the peak lies on ground in a cast shadow, not on a dark
#: object. Measured with ``energy_gain=ENERGY_GAIN, prop_margin=2`` at the body peaks (verification >= 3) where the
#: rule would move the click across the outline (docs/results/observer.md): 0.14-0.42 where it goes from the shadow
#: onto the object (occluded's Mean and Random view 2, split's Random view 3, panorama's Mean and Random view 1),
#: 0.00-0.02 where it leaves a dark or glass object for the blur outside its outline (split's Mean view 3 and
#: Transparent view 1, panorama's Mean, Random and Transparent) -- but also 0.03 on gravel's Ours view 3, a dark cast
#: shadow with little ground texture left, whose click the gate then leaves on the shadow. A glass object shows the
#: ground's texture through it: split's glass vase of view 1 reads 0.12 at the peak the default maps give, so
#: ``click="thing"`` with the default maps still moves that click off it (25 % confused).
CLICK_CAST_SHADOW = 0.1


def core_click(evidence: np.ndarray, y: np.ndarray, x: np.ndarray, radius: float,
               level: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Where a person clicks the thing they identified at ``(y, x)`` (feature pixels; the peak of its object
    evidence ``evidence``, ``(h, w)``): its centre of gravity, kept inside its core.

    The thing is the connected region of ``evidence >= level`` (:data:`CLICK_EVIDENCE`) holding the peak, within
    ``radius`` px of it (the largest object the participant expects: nothing farther belongs to one object). The
    click aims at its centre of gravity -- saccades to a shape land near its centre of gravity, precisely and
    whatever its outline (Kowler & Blaser 1995, Vision Res. 35; McGowan, Kowler, Sharma & Chubb 1998, Vision Res.
    38; Vishwanath & Kowler 2003, Vision Res. 43), and the hand follows the eye (pointing and clicking go to the
    fixated target) -- and lands on the place of the thing's core nearest to it: the places whose distance to the
    thing's outline is at least :data:`CLICK_CORE_DEPTH` of the largest (a ring's centre of gravity lies in its
    hole, a crescent's outside it; a person clicks the body). So the click lands inside the identified blob, not on
    its rim where the evidence may peak (an object's dark side meeting its own shadow), and never reads the mask.
    A start whose evidence is below ``level`` is returned unchanged. Deterministic; vectorised over unique starts.

    >>> e = np.zeros((40, 40)); e[10:30, 5:35] = 3.0; e[10:30, 30:35] = 9.0  # a bar whose right end is strongest
    >>> [int(v[0]) for v in core_click(e, np.array([20]), np.array([33]), 30.0)]
    [19, 19]
    """
    from scipy import ndimage

    level = CLICK_EVIDENCE if level is None else level
    h, w = evidence.shape
    y, x = np.asarray(y, int).copy(), np.asarray(x, int).copy()
    rr = int(math.ceil(radius))
    wy, wx = np.mgrid[-rr:rr + 1, -rr:rr + 1]
    inside = wy ** 2 + wx ** 2 <= radius * radius
    starts = np.unique(np.stack([y, x], 1), axis=0)
    for sy, sx in starts:
        if evidence[sy, sx] < level:
            continue
        y0, x0 = max(0, sy - rr), max(0, sx - rr)
        win = evidence[y0:min(h, sy + rr + 1), x0:min(w, sx + rr + 1)]
        disc = inside[y0 - (sy - rr):y0 - (sy - rr) + win.shape[0], x0 - (sx - rr):x0 - (sx - rr) + win.shape[1]]
        lab, _ = ndimage.label((win >= level) & disc)
        thing = lab == lab[sy - y0, sx - x0]
        ty, tx = np.nonzero(thing)
        gy, gx = ty.mean(), tx.mean()
        depth = ndimage.distance_transform_edt(np.pad(thing, 1))[1:-1, 1:-1]
        core = depth >= CLICK_CORE_DEPTH * depth.max()
        cy, cx = np.nonzero(core)
        k = int(np.argmin((cy - gy) ** 2 + (cx - gx) ** 2))
        at = (y == sy) & (x == sx)
        y[at], x[at] = y0 + cy[k], x0 + cx[k]
    return y, x


def _climb(v: np.ndarray, y: np.ndarray, x: np.ndarray, steps: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Steepest ascent on ``v`` from the points ``(y, x)`` (8-neighbourhood) to a local maximum."""
    h, w = v.shape
    pad = np.pad(v, 1, mode="constant", constant_values=-np.inf)
    dy, dx = np.mgrid[-1:2, -1:2]
    dy, dx = dy.ravel(), dx.ravel()
    y, x = y.astype(int).copy(), x.astype(int).copy()
    for _ in range(steps):
        nb = pad[y[:, None] + 1 + dy[None], x[:, None] + 1 + dx[None]]
        k = nb.argmax(1)
        moved = nb[np.arange(len(y)), k] > pad[y + 1, x + 1]
        if not moved.any():
            break
        y = np.where(moved, y + dy[k], y)
        x = np.where(moved, x + dx[k], x)
    return np.clip(y, 0, h - 1), np.clip(x, 0, w - 1)


# --------------------------------------------------------------------------------------------------------------
# search
# --------------------------------------------------------------------------------------------------------------


@dataclass
class SearchResult:
    """``n`` simulated trials of one stimulus. Arrays have shape ``(n,)``."""

    clicked: np.ndarray  # bool: the observer clicked within the time limit
    timed_out: np.ndarray  # bool: no click within the limit
    click_x: np.ndarray  # int image pixel column of the click (-1 when timed out)
    click_y: np.ndarray  # int image pixel row (-1 when timed out)
    rt_s: np.ndarray  # float seconds from onset to the click; the time limit for a timeout
    fixations: np.ndarray  # int fixations made
    found: np.ndarray | None = None  # bool: the click hit the mask (None without a mask)


def simulate_search(image: np.ndarray | None, n: int = 200, seed: int = 0, config: ObserverConfig | None = None,
                    mask: np.ndarray | None = None, cells: Cells | None = None,
                    background: np.ndarray | None = None) -> SearchResult:
    """Simulate ``n`` independent searches of ``image`` (sRGB ``(H, W, 3)``); score clicks against ``mask``
    (``(H, W)`` bool, optional; never seen by the observer). Deterministic for a given ``seed``. ``cells``: the
    image's :func:`make_cells` when already computed (``image`` is then not read; the study client caches them).
    ``background``: the same view without the object (sRGB, same size), when the stimulus set has it: the
    background statistics every place is compared with (module docstring, step 1); never the object's place.

    Vectorised over the ``n`` trials: each step verifies the current fixation of every active trial (steps 5-6
    of the module docstring) and moves the others (step 4)."""
    cfg = config or ObserverConfig()
    cfg.validate()
    if n < 1:
        raise CamoError(f"observer: n must be >= 1, got {n}")
    cells = cells if cells is not None else make_cells(image, cfg, background=background)
    rng = np.random.default_rng(seed)
    G, V, pos = np.maximum(cells.g, 0.0), cells.v, cells.pos_deg
    C = len(G)
    dist = np.sqrt(((pos[:, None, :] - pos[None, :, :]) ** 2).sum(-1))  # (C, C) degrees
    vis = 1.0 / (1.0 + dist / cfg.e2_deg)  # visibility of cell j from fixation i
    ior_k = cfg.ior_strength * np.exp(-dist ** 2 / (2 * cfg.ior_radius_deg ** 2))
    centre = np.array([cells.width_deg / 2, cells.height_deg / 2])
    if cfg.start == "centre":
        fix = np.full(n, int(np.argmin(((pos - centre) ** 2).sum(-1))))
    else:
        fix = rng.integers(C, size=n)
    t = np.zeros(n)
    ior = np.zeros((n, C))
    clicked = np.zeros(n, bool)
    done = np.zeros(n, bool)
    click_cell = np.full(n, -1)
    rt = np.full(n, cfg.time_limit_s)
    nfix = np.zeros(n, int)
    max_steps = int(math.ceil(cfg.time_limit_s / cfg.fixation_s)) + 1
    for step in range(max_steps):
        act = np.flatnonzero(~done)
        if act.size == 0:
            break
        t[act] += cfg.fixation_s
        nfix[act] += 1
        over = t[act] > cfg.time_limit_s  # this fixation would end after the limit: timeout
        done[act[over]] = True
        act = act[~over]
        if act.size == 0:
            break
        f = fix[act]
        if step == 0:  # onset: the eyes are where the fixation point was; the first saccade is planned (no check)
            pri = vis[f] * G[None, :] + cfg.look_noise * rng.standard_normal((act.size, C))
            fix[act] = pri.argmax(1)
            continue
        if cfg.decision == "diffusion":  # verify the fixated place: evidence accumulated to a bound, in time
            a_, k_ = diffusion_parameters(cfg)
            yes, dt = diffusion_decision(k_ * (V[f] - cfg.criterion), a_, rng)
            t[act] += dt
            over = t[act] > cfg.time_limit_s  # still deciding at the limit: timeout
            done[act[over]] = True
            act, f, yes = act[~over], f[~over], yes[~over]
            if act.size == 0:
                break
        else:  # one noisy look against the criterion, no decision time
            yes = V[f] + cfg.verify_noise * rng.standard_normal(act.size) > cfg.criterion
        if yes.any():
            a, c = act[yes], f[yes]
            d = np.sqrt(((cells_click_deg(cells, c) - centre) ** 2).sum(-1))
            when = t[a] + cfg.verify_s + cfg.fitts_a_s + cfg.fitts_b_s * np.log2(d / cfg.fitts_width_deg + 1.0)
            ok = when <= cfg.time_limit_s
            clicked[a[ok]] = True
            click_cell[a[ok]] = c[ok]
            rt[a[ok]] = when[ok]
            done[a] = True
        a, f = act[~yes], f[~yes]
        if a.size:
            ior[a] += ior_k[f]
            pri = vis[f] * G[None, :] + cfg.look_noise * rng.standard_normal((a.size, C)) - ior[a]
            fix[a] = pri.argmax(1)
    cx = np.where(clicked, cells.click_px[np.maximum(click_cell, 0), 0], -1)
    cy = np.where(clicked, cells.click_px[np.maximum(click_cell, 0), 1], -1)
    res = SearchResult(clicked, ~clicked, cx, cy, np.where(clicked, rt, cfg.time_limit_s), nfix)
    if mask is not None:
        m = np.asarray(mask).astype(bool)
        if m.shape != cells.image_shape:
            raise CamoError(f"observer: mask is {m.shape[1]}x{m.shape[0]} but the image is "
                            f"{cells.image_shape[1]}x{cells.image_shape[0]}")
        res.found = clicked & m[np.maximum(cy, 0), np.maximum(cx, 0)]
    return res


#: Correction of the bound of the discrete walk that samples a diffusion (Siegmund 1979's corrected diffusion
#: approximation: a Gaussian walk overshoots a bound by ~0.5826 of its step's standard deviation on average, so the
#: walk's bound is set that much lower to cross where the continuous process would).
_OVERSHOOT = 0.5826


def diffusion_parameters(config: ObserverConfig) -> tuple[float, float]:
    """``(a, k)`` of the verification's diffusion (``config.decision == "diffusion"``): bounds at ``+-a`` with unit
    noise per sqrt(second), ``a = sqrt(decision_time_s)`` (the mean decision time at zero drift is ``a^2``), and
    drift ``k (V - criterion)`` per second, ``k = 1.702 / (2 a verify_noise)``: the probability of the "object"
    bound, ``1 / (1 + exp(-2 a k (V - criterion)))``, is then the logistic that matches the normal ogive
    ``Phi((V - criterion) / verify_noise)`` of the one-shot rule to within 0.01 (Haley's 1.702)."""
    a = math.sqrt(config.decision_time_s)
    return a, 1.702 / (2.0 * a * config.verify_noise)


def diffusion_decision(drift: np.ndarray, bound: float, rng: np.random.Generator, step_s: float = 0.005,
                       max_s: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """First passage of ``dX = drift dt + dW`` from 0 to ``+-bound`` (per element of ``drift``, 1/s): ``(upper,
    time_s)``, ``upper`` bool (the "object" bound), ``time_s`` the decision time.

    Wald's sequential probability ratio test in continuous time, the drift-diffusion model of two-choice
    decisions (Ratcliff 1978; Bogacz et al. 2006, Psychol. Rev. 113): ``P(upper) = 1 / (1 + exp(-2 bound drift))``
    and the mean decision time ``(bound / drift) tanh(bound drift)`` (``bound^2`` at zero drift) -- weak evidence
    gives slow decisions and errors on both sides, strong evidence fast, sure ones. Sampled as a Gaussian walk of
    ``step_s`` with the bound lowered by the walk's mean overshoot (:data:`_OVERSHOOT`); a walk still between the
    bounds after ``max_s`` takes the side it is on (no case of the observer's settings comes near: at zero drift
    and a 0.5 s mean decision time the chance is below 1e-20).

    >>> up, t = diffusion_decision(np.full(20000, 2.0), 0.7, np.random.default_rng(0))
    >>> round(float(up.mean()), 2), round(1 / (1 + math.exp(-2 * 0.7 * 2.0)), 2)
    (0.94, 0.94)
    >>> round(float(t.mean()), 2), round(0.7 / 2.0 * math.tanh(0.7 * 2.0), 2)
    (0.31, 0.31)
    """
    drift = np.asarray(drift, np.float64)
    x = np.zeros(drift.shape)
    t = np.zeros(drift.shape)
    b = max(bound - _OVERSHOOT * math.sqrt(step_s), 0.5 * bound)
    live = np.flatnonzero(np.ones(drift.shape, bool))
    sd = math.sqrt(step_s)
    for _ in range(int(math.ceil(max_s / step_s))):
        if live.size == 0:
            break
        x[live] += drift[live] * step_s + sd * rng.standard_normal(live.size)
        t[live] += step_s
        live = live[np.abs(x[live]) < b]
    return x > 0, t


def cells_click_deg(cells: Cells, idx: np.ndarray) -> np.ndarray:
    """``(k, 2)`` click points of cells ``idx`` in degrees from the image's top-left corner."""
    H, W = cells.image_shape
    px = cells.click_px[idx].astype(np.float64) + 0.5
    return np.stack([px[:, 0] / W * cells.width_deg, px[:, 1] / H * cells.height_deg], -1)


@dataclass
class StimulusPrediction:
    """What the observer predicts for one stimulus."""

    p_found: float  # probability of a correct click within the limit
    p_miss: float  # a click off the object (a false verification)
    p_timeout: float  # no click within the limit
    rt_found_s: np.ndarray  # search times of the simulated finds (seconds): the distribution
    rt_all_s: np.ndarray  # time on trial of every simulated trial (timeouts at the limit, misses at the click)
    result: SearchResult
    object_evidence: float  # the largest verification evidence V of a fixation that would click on the object, d'
    time_limit_s: float = 40.0

    def summary(self) -> dict[str, float]:
        f = self.rt_found_s
        return {"p_found": self.p_found, "p_miss": self.p_miss, "p_timeout": self.p_timeout,
                "mean_time_found_s": float(f.mean()) if f.size else math.nan,
                "median_time_found_s": float(np.median(f)) if f.size else math.nan,
                "mean_time_all_s": float(self.rt_all_s.mean()), "median_time_all_s": float(np.median(self.rt_all_s)),
                "mean_time_to_find_s": float(self.time_to_find_s.mean()),
                "median_time_to_find_s": float(np.median(self.time_to_find_s)),
                "object_evidence": self.object_evidence}

    @property
    def time_to_find_s(self) -> np.ndarray:
        """Time to find per simulated trial, misses and timeouts at the time limit (the study's Kaplan-Meier
        convention ``miss_censor="limit"``): the search time that only grows as an object gets harder to find."""
        return np.where(self.result.found, self.result.rt_s, self.time_limit_s)


def predict_stimulus(image: np.ndarray, mask: np.ndarray, n: int = 200, seed: int = 0,
                     config: ObserverConfig | None = None, cells: Cells | None = None,
                     background: np.ndarray | None = None, normals: np.ndarray | None = None) -> StimulusPrediction:
    """Probability found and the search-time distribution of one stimulus (``n`` simulated trials);
    ``background``: as in :func:`simulate_search`; ``normals``: as in :func:`evidence_maps`."""
    cfg = config or ObserverConfig()
    cfg.validate()
    cells = cells if cells is not None else make_cells(image, cfg, background=background, normals=normals)
    res = simulate_search(image, n, seed, cfg, mask, cells)
    m = np.asarray(mask).astype(bool)
    on = m[cells.click_px[:, 1], cells.click_px[:, 0]]
    return StimulusPrediction(float(res.found.mean()), float((res.clicked & ~res.found).mean()),
                              float(res.timed_out.mean()), res.rt_s[res.found], res.rt_s.copy(), res,
                              float(cells.v[on].max()) if on.any() else math.nan, cfg.time_limit_s)


# --------------------------------------------------------------------------------------------------------------
# Table I
# --------------------------------------------------------------------------------------------------------------

#: Columns of a per-stimulus prediction table (``predicted.parquet`` of a stimulus set).
PREDICTION_COLUMNS = ("p_found", "p_miss", "p_timeout", "mean_time_found_s", "median_time_found_s",
                      "mean_time_all_s", "median_time_all_s", "mean_time_to_find_s", "median_time_to_find_s",
                      "object_evidence")


def predicted_table(views, by: Sequence[str] = ("method",), trials=None):
    """Table I predicted from per-stimulus predictions (``views``: columns :data:`PREDICTION_COLUMNS` and ``by``),
    per ``by`` group.

    Every stimulus weighs the same (as a scene x method cell of the study does). ``confusion_rate`` = 1 - mean
    p_found; ``p_miss`` / ``p_timeout`` the two ways of not finding. Times: over the simulated finds
    (``mean/median_time_found_s``) and over all trials (timeouts at the limit), from ``trials`` (per simulated
    trial, with the ``by`` columns, ``found`` and ``rt_s``) when given, else the means of the per-stimulus
    figures. ``easy_views``: stimuli found with p >= 0.95 within a median of 2 s (candidates to fix or drop)."""
    import pandas as pd

    out = []
    for key, g in views.groupby(list(by), sort=True):
        key = key if isinstance(key, tuple) else (key,)
        row = dict(zip(by, key))
        row.update(n_views=len(g), n_scenes=int(g["scene"].nunique()) if "scene" in g else 1,
                   confusion_rate=1.0 - float(g["p_found"].mean()),
                   p_miss=float(g["p_miss"].mean()), p_timeout=float(g["p_timeout"].mean()))
        if trials is not None and len(trials):
            t = trials
            for c, v in row.items():
                if c in by:
                    t = t[t[c] == v]
            f = t.loc[t["found"], "rt_s"]
            row.update(mean_time_found_s=float(f.mean()) if len(f) else math.nan,
                       median_time_found_s=float(f.median()) if len(f) else math.nan,
                       mean_time_all_s=float(t["rt_s"].mean()), median_time_all_s=float(t["rt_s"].median()))
        else:
            row.update(mean_time_found_s=float(g["mean_time_found_s"].mean()),
                       median_time_found_s=float(g["median_time_found_s"].median()),
                       mean_time_all_s=float(g["mean_time_all_s"].mean()),
                       median_time_all_s=float(g["median_time_all_s"].median()))
        row["easy_views"] = int(((g["p_found"] >= 0.95) & (g["median_time_found_s"] <= 2.0)).sum())
        out.append(row)
    return pd.DataFrame(out)


#: The only human figures the observer is checked against: Table I of the paper ("Hiding in plain sight", the
#: perceptual study of Section IV: 71 participants, GANmouflage's click-to-find protocol, 40 s per trial, one
#: formal trial per scene): method -> (confusion rate, mean time of finds s, median time s). Owens et al. (2014)
#: and GANmouflage (Guo et al. 2023) report their own studies, but their tables could not be read here, so no
#: figure of theirs is used (docs/results/observer.md).
PAPER_TABLE_I = {"Transparent": (0.0010, 1.79, 1.86), "Random [6]": (0.1577, 4.65, 3.92),
                 "GANmouflage [7]": (0.1299, 3.61, 3.39), "2D Diffusion": (0.0911, 3.03, 3.48),
                 "Ours": (0.5411, 8.02, 9.41)}
#: The human range for plainly visible objects read off that table (Transparent, Random, GANmouflage, 2D
#: Diffusion): confusion at most 20 %, mean time of finds 1.5-6 s.
HUMAN_VISIBLE = {"max_confusion": 0.20, "mean_time_s": (1.5, 6.0)}
