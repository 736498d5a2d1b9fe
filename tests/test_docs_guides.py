"""Half of the guides' examples (the site's Guides section; the other half: tests/test_docs_guides_second.py), in
files of their own beside tests/test_docs.py so that `--dist loadfile` shares the site's examples out over the
workers."""
import pytest
from test_docs import REPO, guides_half, run_examples

PAGES = guides_half(0)


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(REPO)) for p in PAGES])
@pytest.mark.slow
def test_examples_run(page, tmp_path):
    run_examples(page, tmp_path)
