"""Unit layer: docs/protocol.md's table of simulated error rates and power is generated from the
committed counts of experiments/tuning_power.py."""


def test_the_protocols_simulation_table_is_generated_from_the_committed_counts():
    """docs/protocol.md's table of error rates and power is the one experiments/tuning_power.py
    renders from docs/evidence/tuning_power.csv, and that file holds every cell of the simulation
    (so the table cannot drift from its evidence, nor the evidence from the code's cells)."""
    import csv

    from experiments.tuning_power import RULES, cells, table
    from tests.helpers import REPO

    evidence = REPO / "docs" / "evidence" / "tuning_power.csv"
    text = (REPO / "docs" / "protocol.md").read_text()
    begin = text.index("<!-- generated: python -m experiments.tuning_power")
    inside = text[text.index("\n", begin) + 1 : text.index("<!-- end of generated table -->")]
    assert inside.strip() == table(evidence).strip()
    with open(evidence) as file:
        rows = list(csv.DictReader(file))
    found = {
        (r["null"], r["design"], int(r["variants"]), int(r["trials"]), int(r["studies"]))
        + (float(r["effect"]), int(r["sims"]), r["rule"])
        for r in rows
    }
    for cell in cells(1600):
        for rule in RULES:
            assert cell.key + (cell.sims, rule) in found, (cell, rule)


def test_the_row_marked_physgrad_is_what_physgrad_compare_does():
    """The table marks one design and rule as physgrad's: four independent studies (compare.studies'
    default) and across_studies' defaults (a majority, every median on its side)."""
    import inspect

    from experiments.tuning_power import PHYSGRAD
    from physgrad.comparison.spec import SETTINGS
    from physgrad.replication import across_studies

    design, studies, rule = PHYSGRAD
    assert (design, rule) == ("independent", "consistent")
    assert SETTINGS["studies"][0] == studies
    defaults = inspect.signature(across_studies).parameters
    assert defaults["need"].default is None and defaults["same_side"].default is True


def test_the_study_luck_table_is_generated_from_the_committed_counts():
    """docs/protocol.md's table of the test between studies is the one experiments/study_luck.py
    renders from docs/evidence/study_luck.csv, which holds every model of the simulation at every
    level, physgrad's marked."""
    import csv

    from experiments.study_luck import BEGIN, END, RULES, models, table
    from physgrad.replication import STUDY_ALPHA
    from tests.helpers import REPO

    evidence = REPO / "docs" / "evidence" / "study_luck.csv"
    text = (REPO / "docs" / "protocol.md").read_text()
    inside = text[text.index("\n", text.index(BEGIN)) + 1 : text.index(END)]
    assert inside.strip() == table(evidence).strip()
    assert f"**{STUDY_ALPHA:g}: physgrad**" in inside
    with open(evidence) as file:
        found = {tuple(r.values())[:10] for r in csv.DictReader(file)}
    for model in models(2000):
        for rule in RULES:
            assert (*model.key, rule) in found, (model, rule)
