"""vehjax.runtime.progress: the one progress bar of run and tune: disabled writes nothing; without tqdm
a text line on stderr, rewritten in place, ended once by a newline."""

import builtins

import pytest

from vehjax.runtime.progress import Progress, text_bar


@pytest.fixture
def no_tqdm(monkeypatch):
    real = builtins.__import__

    def fake(name, *args, **kwargs):
        if name.startswith("tqdm"):
            raise ImportError(name)
        return real(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake)


def test_disabled_writes_nothing(capsys):
    bar = Progress(3, "x", False)
    bar.update(1, "p", "t")
    bar.close()
    assert capsys.readouterr().err == ""


def test_text_line_without_tqdm(no_tqdm, capsys):
    bar = Progress(2, "job", True, first_text="job [..] 0/2")
    bar.update(1, "ignored", "job 1/2")
    bar.update(2, "ignored", "job 2/2")
    bar.close()  # already ended at the last unit: nothing more
    err = capsys.readouterr().err
    assert err.startswith("\rjob [..] 0/2, ") and "\rjob 1/2, " in err and "\rjob 2/2, " in err
    assert err.endswith(" s\n") and err.count("\n") == 1


def test_text_line_closed_early_ends_with_the_latest_words(no_tqdm, capsys):
    bar = Progress(10, "fit", True, interval=60.0)  # throttled: only close writes
    bar.update(1, "", "fit 1/10")
    bar.update(2, "", "fit 2/10")
    bar.close()
    err = capsys.readouterr().err
    assert "fit 1/10" not in err and err.startswith("\rfit 2/10, ") and err.endswith(" s\n")


def test_text_bar():
    assert text_bar(0, 3, 6) == "......" and text_bar(3, 3, 6) == "######"
    assert text_bar(1, 2, 4) == "##.."
