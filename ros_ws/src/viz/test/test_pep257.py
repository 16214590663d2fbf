# The ament_pep257 template test. The project writes a docstring's summary on its opening
# line (PEP 257 allows either; D212), so D213, which asks for the second line, is off.
import pytest
from ament_pep257.main import main


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257():
    rc = main(argv=['.', 'test', '--add-ignore', 'D213'])
    assert rc == 0, 'Found code style errors / warnings'
