"""The report names tasks from data (report/tasks.json), and a task it does not list still gets a name, a place
after the paper's two and unnumbered trace figures: a new task family needs no code in the report."""

from __future__ import annotations

from vlmproprio.report.data import paper_figure, task_label, task_order


def test_listed_tasks_have_their_labels_and_the_papers_figures():
    assert task_label("door") == "Door opening" and paper_figure("door") == 7
    assert task_label("pick_place") == "Bin pick-placing" and paper_figure("pick_place") == 8
    assert task_label("stack") == "Stacking" and paper_figure("stack") is None
    assert task_label("all") == "All episodes"


def test_an_unlisted_task_is_named_from_its_own_name_and_comes_last():
    assert task_label("nut_assembly") == "Nut assembly" and paper_figure("nut_assembly") is None
    assert task_label(None) == ""
    assert task_order({"zeta", "stack", "pick_place", "door", "all", "nut_assembly"}) == [
        "door",
        "pick_place",
        "stack",
        "nut_assembly",
        "zeta",
    ]
