"""The other half of the guides' examples (tests/test_docs_guides.py says why they are split)."""
import pytest
from test_docs import REPO, guides_half, run_examples

PAGES = guides_half(1)


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(REPO)) for p in PAGES])
@pytest.mark.slow
def test_examples_run(page, tmp_path):
    run_examples(page, tmp_path)
