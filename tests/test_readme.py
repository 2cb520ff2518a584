"""README claims that once said more than their measurement (issue 31, findings 4 and 9): each
sentence that makes such a comparison must say what it measures."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def sentences(text: str) -> list[str]:
    """Table rows and list items whole; prose paragraphs split into sentences."""
    units, para = [], []
    for line in text.splitlines() + [""]:
        if line.startswith(("|", "- ")) or not line.strip():
            if para:
                units += re.split(r"(?<=[.;])\s+(?=[A-Z(`])", " ".join(para))
                para = []
            if line.strip():
                units.append(line)
        else:
            para.append(line.strip())
    return units


def kernel_claims(text: str) -> list[str]:
    """Sentences that put the Denoiser's time against its own kernel's without naming both
    resolutions (it runs at half resolution from 256 px; the kernel ratio was read at full)."""
    return [s for s in sentences(text)
            if re.search(r"\bits (full-resolution )?kernel", s) and re.search(r"\d\.\d+x", s)
            and not ("half resolution" in s and "equal resolution" in s)]


def flicker_claims(text: str) -> list[str]:
    """Sentences that say the TemporalDenoiser flickers less than OIDN without naming tRMAE, the
    one measure that shows it, or that cite tPSNR or FLIP without saying they are worse."""
    return [s for s in sentences(text) if "OIDN" in s and ("Temporal" in s or "flicker" in s)
            and (("flicker" in s and "tRMAE" not in s) or (re.search(r"tPSNR|FLIP", s) and "worse" not in s))]


def test_the_denoiser_against_its_kernel_says_what_differs():
    assert not kernel_claims(README.read_text())
    old = ("the guided Denoiser runs end to end at its kernel's speed as one fused pipeline (0.89-1.21x its kernel, "
           "21-26x faster than OIDN \"high\" from 512² to 4K on 2 cores), with tiles for bounded memory.")
    assert kernel_claims(old)  # the sentence of finding 9 is caught


def test_the_temporal_claim_names_its_measure():
    assert not flicker_claims(README.read_text())
    old = ("The TemporalDenoiser flickers less than OIDN and than the per-frame Denoiser on every sequence "
           "(FLIP, tPSNR and the error on newly revealed pixels).")
    assert flicker_claims(old)  # the sentence of finding 4 is caught


INTERNAL = re.compile(r"\b(issue \d+|issues? #?\d+|stops?|judged|run \d+|runs \d+)\b", re.IGNORECASE)


def test_the_readme_is_a_front_door():
    """At most 160 lines, none over 200 characters, no internal words (issue numbers, "stop",
    "judged", run numbers): a user reads it, not the team."""
    text = README.read_text()
    lines = text.splitlines()
    assert len(lines) <= 160
    assert [n for n, line in enumerate(lines, 1) if len(line) > 200] == []
    assert [m.group(0) for m in INTERNAL.finditer(text)] == []
    assert INTERNAL.search("the accuracy gap is the open problem (issue 28)")  # the old README's words
    assert INTERNAL.search("run 9, frames at the accuracy run's spacing")


def test_every_figure_in_the_readme_has_its_page_and_command():
    """Each line of the README that states a measured figure (a ratio or a unit) links a page under
    docs/ that exists and opens with the command that measured it."""
    root = README.parent
    figure = re.compile(r"\d(\.\d+)?\s?(x|ms|s|%)\b|\b0\.\d{3,}")
    fenced = False
    for line in README.read_text().splitlines():
        fenced ^= line.startswith("```")
        if fenced or line.startswith("```") or not figure.search(line):
            continue  # code blocks hold commands, not results
        pages = re.findall(r"\((docs/[\w/.-]+\.md)[)#]", line)
        assert pages, f"a figure without its page: {line[:120]}"
        for page in pages:
            head = "\n".join((root / page).read_text().splitlines()[:20])
            assert re.search(r"(python scripts/\w+\.py|torchgi \w+)", head), f"{page} does not open with its command"


def test_the_quick_start_runs(tmp_path, monkeypatch, capsys):
    """The README's Python quick start runs as written (from a folder holding the repository's
    configs), its first render at a smaller size to keep the suite short, and the errors it prints
    say what it promises: the Denoiser's relMSE well under the noisy render's."""


    pytest.importorskip("embreex")
    pytest.importorskip("OpenEXR")
    code = re.search(r"```python\n(.*?)```", README.read_text(), re.DOTALL).group(1)
    assert "torchgi.scenes.cornell(128)" in code and "spp=256" in code
    code = code.replace("torchgi.scenes.cornell(128)", "torchgi.scenes.cornell(32)").replace("spp=256", "spp=16")
    (tmp_path / "configs").symlink_to(README.parent / "configs")
    monkeypatch.chdir(tmp_path)
    exec(compile(code, "README.md", "exec"), {})  # noqa: S102 - the README's own code
    assert (tmp_path / "out" / "noisy.exr").is_file()
    noisy, denoised = (float(v) for v in re.findall(r"tensor\(([\d.e-]+)\)", capsys.readouterr().out))
    assert denoised < 0.5 * noisy, (noisy, denoised)


def test_the_filters_alone_recipe_runs_and_has_the_error_it_says(capsys):
    """docs/api.md's recipe around the bare filters runs, and its explanation holds: it has
    several times the Denoiser's error (on the page's own render: smaller ones have too noisy a
    reference to show it)."""
    pytest.importorskip("embreex")
    text = (README.parent / "docs" / "api.md").read_text()
    code = re.search(r"## The filters alone.*?```python\n(.*?)```", text, re.DOTALL).group(1)
    exec(compile(code, "docs/api.md", "exec"), {})  # noqa: S102 - the page's own code
    recipe, denoiser = (float(v) for v in re.findall(r"tensor\(([\d.e-]+)\)", capsys.readouterr().out))
    assert recipe > 3 * denoiser


def test_the_which_to_use_table_names_every_registered_method_and_no_other():
    """The README's table reads the registry's names (``torchgi.methods.names()``)."""
    from torchgi import methods

    section = README.read_text(encoding="utf-8").split("## Which to use", 1)[1].split("\n## ", 1)[0]
    named = set(re.findall(r'\("([a-z]+)"\)', section))
    assert named == set(methods.names())
