"""Markers for choosing what to run (registered in pyproject.toml).

`make test` runs everything; `make test-fast` deselects ``datasets``, ``browser``, ``fuzz`` and
``slow``. Set here, by module name: ``browser`` on ``test_web_browser*`` (a real browser),
``fuzz`` on ``test_fuzz_*``, ``slow`` on the tests of :data:`SLOW` and on any test that says so
itself. ``datasets`` is set here too, so that no test that reads ../shared
can be left out of it by oversight: a test is marked when its code, a fixture it uses, a parameter
it is given or a module-level helper it calls (transitively) refers to a path inside ../shared held
by its module or names ../shared in a string (the reason it skips without it), or when it carries a
``skipif`` whose reason names ../shared.
"""

from __future__ import annotations

import inspect
import types
from collections.abc import Iterable
from pathlib import Path

import pytest

SHARED = (Path(__file__).resolve().parents[1].parent / "shared").resolve()

SLOW = frozenset(
    (
        "test_alignment.py::test_correct_align_refused_writes_nothing",
        "test_atomic.py::test_a_killed_writer_leaves_only_a_recognisable_temporary_file",
        "test_check_once.py::test_a_damaged_stored_check_is_refused_with_the_map_named",
        "test_check_once.py::test_a_session_matches_its_scans_when_it_starts_and_never_per_correction",
        "test_check_once.py::test_a_stored_check_of_other_scans_or_another_setting_is_not_used",
        "test_check_once.py::test_prepared_the_first_correction_makes_nothing_of_its_own",
        "test_cli.py::test_console_script_help_and_exit_code",
        "test_cli_correct.py::test_bad_input_as_a_real_process",
        "test_cli_correct.py::test_correct_moves_the_second_pass_onto_the_first",
        "test_cli_correct.py::test_export_formats",
        "test_cli_correct.py::test_keep_going_applies_the_rest_and_lists_rejections",
        "test_cli_correct.py::test_rejection_stops_the_run_and_writes_nothing",
        "test_cli_correct.py::test_session_is_written_and_its_corrections_replay_to_the_same_map",
        "test_cli_correct.py::test_undo_in_a_script_restores_the_input_map",
        "test_cli_outputs.py::test_a_directory_as_output_is_one_line_exit_2",
        "test_cli_outputs.py::test_a_real_full_or_read_only_file_system",
        "test_cli_outputs.py::test_a_session_that_cannot_be_written_leaves_no_output",
        "test_cli_outputs.py::test_an_output_fault_is_one_line_exit_2_and_nothing_left",
        "test_cli_outputs.py::test_an_output_that_cannot_be_renamed_takes_the_new_session_with_it",
        "test_cli_outputs.py::test_an_output_that_is_the_input_is_refused_unless_force",
        "test_colocation_consistency.py::test_a_colocation_the_scans_agree_with_stays_a_colocation",
        "test_colocation_consistency.py::test_a_same_stretch_colocation_on_a_loose_chain_is_kept_on_one_line",
        "test_contradicted_relations.py::test_a_false_statement_after_true_ones_is_the_one_that_yields",
        "test_contradicted_relations.py::test_a_false_statement_yields_to_the_true_ones_that_contradict_it",
        "test_contradicted_relations.py::test_a_statement_that_yields_is_solved_alike_again",
        "test_contradicted_relations.py::test_true_corrections_that_agree_are_unchanged_by_the_kernel",
        "test_correction_end_to_end.py::test_any_sequence_equals_the_surviving_corrections_from_scratch",
        "test_correction_end_to_end.py::test_bad_drawings_change_nothing_in_a_real_session",
        "test_correction_end_to_end.py::test_lines_are_undirected",
        "test_correction_end_to_end.py::test_newest_of_two_drawn_corrections_changes_the_map",
        "test_correction_guard.py::test_different_stretches_are_left_to_the_solves_not_to_their_lengths",
        "test_correction_guard.py::test_heading_jump_loop_repaired_by_colocations_never_gets_worse",
        "test_correction_guard.py::test_long_colocation_of_diverging_copies_ends_on_one_line",
        "test_corrections_file.py::test_round_trip_is_exact",
        "test_demo.py::test_demo_command_prints_the_table",
        "test_demo.py::test_demo_repairs_the_room",
        "test_docs_citations.py::test_citations_name_the_document_by_its_path",
        "test_docs_citations.py::test_every_cited_section_exists",
        "test_evaluation.py::test_evaluate_command",
        "test_evaluation.py::test_quick_evaluation_repairs_and_reports",
        "test_full_evaluation.py::test_a_person_drawing_past_the_ends_and_beside_the_wall_is_still_understood",
        "test_interpret.py::test_index_on_a_large_random_map",
        "test_interpret.py::test_index_returns_exactly_the_brute_force_set",
        "test_io.py::test_garbage_lines_only_ever_raise_input_error",
        "test_kill_trials.py::test_a_few_kill_trials",
        "test_metrics.py::test_matplotlib_is_imported_only_for_the_heat_map",
        "test_odometry_check.py::test_a_correction_across_the_jump_turns_the_map_at_the_jump",
        "test_odometry_check.py::test_a_heading_jump_is_found_at_its_step_and_only_there",
        "test_odometry_check.py::test_slow_drift_widens_nothing_and_the_check_can_be_turned_off",
        "test_oracle.py::test_the_full_evaluation_runs_with_the_oracle_and_accepts_every_drawing",
        "test_oracle.py::test_the_oracle_selects_the_labelled_points_of_the_passes_drawn_on",
        "test_plot.py::test_before_after_small_png_and_svg",
        "test_plot.py::test_heat_map",
        "test_plot.py::test_importing_the_package_does_not_import_matplotlib",
        "test_plot.py::test_information_matrix_figure",
        "test_public_api.py::test_a_library_import_pulls_neither_extra",
        "test_public_api.py::test_a_map_without_points_still_shows_itself",
        "test_public_api.py::test_a_missing_extra_in_a_real_process_exits_2_with_one_line",
        "test_public_api.py::test_load_correct_save_through_the_public_api",
        "test_public_api.py::test_map_shows_itself_as_png_and_html",
        "test_rosbag.py::test_bad_bags_are_input_errors_naming_the_file",
        "test_rosbag.py::test_slam_on_a_bad_bag_is_one_line_exit_2_and_writes_nothing",
        "test_session.py::test_sigkill_during_a_solve_loses_nothing_committed",
        "test_session_integrity.py::test_a_payload_with_arrays_is_the_text_json_dumps_writes_of_its_lists",
        "test_session_integrity.py::test_malformed_values_are_input_errors_or_change_nothing",
        "test_session_loops.py::test_refusals_change_nothing",
        "test_sim.py::test_human_straightens_a_bent_pass",
        "test_sim.py::test_repair_through_a_session_counts_rejections",
        "test_solver.py::test_gil_is_released_while_solving",
        "test_solver.py::test_random_graphs_never_crash",
        "test_synthetic.py::test_chain_builds_the_100k_scale_graph",
        "test_unchecked_alternative.py::test_a_jump_the_scans_cannot_see_is_kept_where_it_happened",
        "test_unchecked_alternative.py::test_where_the_scans_checked_every_step_nothing_changes",
        "test_web_align.py::test_align_keeps_the_corrections_and_undo_returns_to_the_map_before",
        "test_web_api.py::test_demo_points_to_the_serve_command",
        "test_web_api.py::test_host_wait_wakes_on_change_and_on_close",
        "test_web_api.py::test_inconsistency_arrives_after_each_change",
        "test_web_api.py::test_interpret_previews_and_changes_nothing",
        "test_web_api.py::test_other_requests_are_answered_while_a_correction_computes",
        "test_web_loops.py::test_a_map_without_loop_closures_has_none_to_reject",
        "test_web_map_info.py::test_numpy_indices_a_good_verdict_and_entries_that_are_not_ranges",
        "test_web_map_info.py::test_the_comparison_and_which_poses_the_map_holds",
        "test_web_security.py::test_ctrl_c_stops_the_server_cleanly",
        "test_web_security.py::test_real_server_guards_host_and_token_and_chunked_bodies",
        "test_web_security.py::test_sigkill_during_a_correction_loses_nothing_acknowledged",
        "test_web_security.py::test_the_command_refuses_a_tokenless_server_off_loopback",
        "test_web_security.py::test_the_real_no_token_server_refuses_a_foreign_origin",
        "test_web_security.py::test_token_and_no_token_together_are_refused",
    )
)
"""Tests (``module::function``, every parametrization) that took about a second or more on 2 cores
(`pytest --durations=0`, 2026-12-02) and need neither the datasets nor a browser: left out of
`make test-fast` so that it stays a few minutes. A new slow test belongs here or carries
``@pytest.mark.slow``."""


def _is_shared_path(value: object) -> bool:
    """Whether ``value`` is a path (or a list, tuple or dict of them) inside ../shared."""
    if isinstance(value, Path):
        try:
            return value.resolve().is_relative_to(SHARED)
        except (OSError, RuntimeError):
            return False
    if isinstance(value, list | tuple | set | frozenset):
        return any(_is_shared_path(v) for v in value)
    if isinstance(value, dict):
        return any(_is_shared_path(v) for v in value.values())
    return False


def _code_names(code: types.CodeType) -> set[str]:
    """Global names ``code`` and its nested functions refer to."""
    names = set(code.co_names)
    for const in code.co_consts:
        if isinstance(const, types.CodeType):
            names |= _code_names(const)
    return names


def _names_shared(text: object) -> bool:
    """Whether ``text`` is a string that names ../shared (a skip reason, a path)."""
    return isinstance(text, str) and ("../shared" in text or "shared/datasets" in text)


def _code_names_shared(code: types.CodeType) -> bool:
    """Whether a string constant of ``code`` or of its nested functions names ../shared."""
    return any(
        _names_shared(c) or (isinstance(c, types.CodeType) and _code_names_shared(c))
        for c in code.co_consts
    )


def _reaches_shared(module: types.ModuleType, roots: Iterable[object]) -> bool:
    """Whether a function among ``roots`` reaches, through the module's own functions, a
    module-level name holding a path inside ../shared."""
    held = vars(module)
    seen: set[int] = set()
    todo = [r for r in roots if callable(r)]
    while todo:
        f = inspect.unwrap(todo.pop())  # type: ignore[arg-type]
        code = getattr(f, "__code__", None)
        if code is None or id(code) in seen:
            continue
        seen.add(id(code))
        if _code_names_shared(code):
            return True
        for name in _code_names(code):
            value = held.get(name)
            if _is_shared_path(value):
                return True
            if (isinstance(value, types.FunctionType) and value.__module__ == module.__name__) or (
                isinstance(value, type) and value.__module__ == module.__name__
            ):
                todo.extend(
                    [value] if isinstance(value, types.FunctionType) else vars(value).values()
                )
    return False


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if not isinstance(item, pytest.Function):
            continue
        module = item.module
        if module is None:
            continue
        name = module.__name__.rpartition(".")[2]
        if name.startswith("test_web_browser"):
            item.add_marker(pytest.mark.browser)
        if name.startswith("test_fuzz_"):
            item.add_marker(pytest.mark.fuzz)
        if f"{name}.py::{item.originalname}" in SLOW:
            item.add_marker(pytest.mark.slow)
        if item.get_closest_marker("datasets"):
            continue
        roots: list[object] = [item.function]
        fixtures = item._fixtureinfo.name2fixturedefs
        for defs in fixtures.values():
            roots += [d.func for d in defs if getattr(d.func, "__module__", "") == module.__name__]
        params = getattr(getattr(item, "callspec", None), "params", {})
        skips = [m.kwargs.get("reason") for m in item.iter_markers("skipif")]
        if (
            any(_names_shared(r) for r in skips)
            or _is_shared_path(list(params.values()))
            or _reaches_shared(module, roots)
        ):
            item.add_marker(pytest.mark.datasets)
