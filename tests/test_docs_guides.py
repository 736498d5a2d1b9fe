"""The guides' examples (the site's Guides section), in a file of their own beside tests/test_docs.py so that
`--dist loadfile` runs the two halves of the site's examples in two workers."""
import pytest
from test_docs import GUIDES, REPO, RUN, run_examples

PAGES = [p for p in RUN if p in GUIDES]


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(REPO)) for p in PAGES])
@pytest.mark.slow
def test_examples_run(page, tmp_path):
    run_examples(page, tmp_path)
