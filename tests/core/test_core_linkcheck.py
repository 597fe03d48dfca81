"""The fit's self-check of its links (artdef_addon/linkcheck.py) on fits of a known rig that are wrong on purpose."""
import numpy as np
import pytest

import artdef_addon
from artdef_addon import linkcheck, samples


def _owners(r, truth):
    """For each fitted link, the true links it holds most of the faces of (by majority per true link)."""
    T = truth["face_labels"]
    C = np.zeros((r.n_links, T.max() + 1), int)
    np.add.at(C, (r.face_labels, T), 1)
    best = C.argmax(axis=0)
    return [np.flatnonzero((best == l) & (C.sum(axis=0) > 0)).tolist() for l in range(r.n_links)]


@pytest.fixture(scope="module")
def branching():
    return samples.make_with_truth("branching")


def test_a_fit_with_one_link_too_few_names_the_link_holding_two_parts(branching):
    """The branching sample (11 rigid parts) fitted with 10 links: exactly one link holds two true parts,
    and it is the one the notes say needs two rigid motions (its cut in two lowers its rigid error by
    more than ``SPLIT_GAIN``); no link is named as moving with another."""
    scan, truth = branching
    r = artdef_addon.fit(scan, 10)
    two = [l for l, o in enumerate(_owners(r, truth)) if len(o) > 1]
    assert len(two) == 1
    note = [n for n in r.notes if "need two rigid motions" in n]
    assert note and f"link {two[0]} (" in note[0] and "more links" in note[0]
    assert not any("move as one" in n for n in r.notes)
    c = linkcheck.check(scan.vertices, scan.fields(), scan.faces, r.face_labels, r.parents, r.rotations, r.weights)
    assert c.two_motions == two and c.split_gain[two[0]] >= linkcheck.SPLIT_GAIN


def test_a_fit_with_one_link_too_many_names_the_spare_link(branching):
    """With 12 links every true part keeps a link of its own and one link is spare: the notes name it
    as moving with the link its faces' skin belongs to, and suggest fewer links; nothing needs two motions."""
    scan, truth = branching
    r = artdef_addon.fit(scan, 12)
    owners = _owners(r, truth)
    spare = [l for l, o in enumerate(owners) if not o]
    assert all(len(o) <= 1 for o in owners) and len(spare) == 1
    note = [n for n in r.notes if "move as one" in n]
    assert note and f"link {spare[0]} with link " in note[0] and "fewer links" in note[0]
    assert not any("need two rigid motions" in n for n in r.notes)


def test_the_right_fit_is_not_flagged_and_the_note_reaches_the_summary(branching):
    """At the true count (11) no check speaks; a flagged fit's note is in the summary the CLI prints."""
    scan, _ = branching
    r = artdef_addon.fit(scan, 11)
    assert not any(n.startswith("check the rig") for n in r.notes)
    bad = artdef_addon.fit(scan, 10)
    assert "note: check the rig: links that need two rigid motions" in bad.summary()


def test_two_links_turning_together_move_as_one():
    """The relative-rotation rule on hand-made motions: a child that turns with its parent (0.5° apart
    in one field) moves as one with it; one turned 20° against it does not."""
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(3)
    x0 = rng.normal(size=(6, 3))
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    P = 3
    base = Rotation.random(P, random_state=4).as_matrix()
    rot = np.stack([base, base], axis=1)
    rot[1, 1] = base[1] @ Rotation.from_rotvec([0, 0, np.radians(0.5)]).as_matrix()
    c = linkcheck.check(x0, np.zeros((P, 6, 3)), faces, np.array([0, 1]), np.array([-1, 0]), rot)
    assert c.pairs == [(0, 1, pytest.approx(0.5, rel=1e-6))]
    rot[2, 1] = base[2] @ Rotation.from_rotvec([np.radians(20.0), 0, 0]).as_matrix()
    c = linkcheck.check(x0, np.zeros((P, 6, 3)), faces, np.array([0, 1]), np.array([-1, 0]), rot)
    assert c.pairs == [] and c.pair_degrees[1] == pytest.approx(20.0, rel=1e-6)
