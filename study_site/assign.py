"""Trial plans: which stimulus each participant sees, in which order.

Protocol (GANmouflage / paper Sec. IV-D): ``PRACTICE_TRIALS`` practice images
first (flagged, excluded from the analysis; drawn only from the set's dedicated
practice stimuli, whose scenes are never formal scenes), then one formal trial per scene.
For each scene the method (condition) is the one whose ``(scene, method)``
cell has been assigned least often so far (ties broken at random), so cells
fill evenly across participants; the view is drawn at random among that cell's
renders; the formal trials are shuffled. Every random choice comes from
``random.Random(participant.seed)`` and the resulting plan is stored.

A cell counts the formal plan items of participants who completed the study or
were seen within ``ASSIGNMENT_HOLD_S`` seconds; abandoned sessions stop holding
their cells after that.
"""

from __future__ import annotations

import random
from datetime import datetime, timedelta

from sqlalchemy import func, or_, select
from sqlalchemy.orm import Session

from study_site.db import Participant, PlanItem
from study_site.stimuli import Stimulus, StimulusSet


def cell_counts(s: Session, now: datetime, hold_s: float, exclude_participant: int | None = None) -> dict:
    """``{(scene, condition id): n}`` of formal plan items that currently hold a cell."""
    cutoff = now - timedelta(seconds=hold_s)
    q = (
        select(PlanItem.scene, PlanItem.condition, func.count())
        .join(Participant, Participant.id == PlanItem.participant_id)
        .where(
            PlanItem.practice.is_(False),
            or_(Participant.completed_at.is_not(None), Participant.last_seen_at >= cutoff),
        )
        .group_by(PlanItem.scene, PlanItem.condition)
    )
    if exclude_participant is not None:
        q = q.where(Participant.id != exclude_participant)
    return {(sc, m): int(n) for sc, m, n in s.execute(q)}


def choose_plan(
    stimuli: StimulusSet, counts: dict, seed: int, n_practice: int
) -> list[tuple[bool, Stimulus]]:
    """Plan as ``[(practice, stimulus), ...]`` in presentation order (pure function of its inputs)."""
    rng = random.Random(seed)
    pool = stimuli.formal_pool()
    formal: list[Stimulus] = []
    for scene in sorted(pool):
        conds = sorted(pool[scene])
        least = min(counts.get((scene, c), 0) for c in conds)
        cond = rng.choice([c for c in conds if counts.get((scene, c), 0) == least])
        formal.append(rng.choice(sorted(pool[scene][cond], key=lambda st: st.view)))
    rng.shuffle(formal)

    practice: list[Stimulus] = []
    if n_practice > 0:
        # dedicated practice stimuli only: their scenes never appear in the formal pool (checked when the
        # set is built and when it is loaded), so practice cannot show where a formal object sits
        cands = sorted(stimuli.practice_pool(), key=lambda st: st.id)
        if not cands:
            raise ValueError("the stimulus set has no practice stimuli")
        if len(cands) >= n_practice:
            practice = rng.sample(cands, n_practice)
        else:
            practice = cands + rng.choices(cands, k=n_practice - len(cands))
            rng.shuffle(practice)
    return [(True, st) for st in practice] + [(False, st) for st in formal]


def create_plan(s: Session, p: Participant, stimuli: StimulusSet, n_practice: int, hold_s: float, now: datetime):
    """Assign and store ``p``'s plan (call inside a serialised write transaction)."""
    counts = cell_counts(s, now, hold_s, exclude_participant=p.id)
    items = []
    for idx, (practice, st) in enumerate(choose_plan(stimuli, counts, p.seed, n_practice)):
        item = PlanItem(
            participant_id=p.id,
            idx=idx,
            practice=practice,
            stimulus_id=st.id,
            reveal_id=st.reveal_id,
            run=st.run,
            scene=st.scene,
            object=st.object,
            method=st.method,
            ablation=st.ablation,
            condition=st.condition,
            label=st.label,
            view=st.view,
            width=st.width,
            height=st.height,
        )
        s.add(item)
        items.append(item)
    return items
