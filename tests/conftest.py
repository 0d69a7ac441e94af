import sys
from pathlib import Path

# Test helper modules (fixtures written in real formats) live beside the tests.
sys.path.insert(0, str(Path(__file__).parent))
