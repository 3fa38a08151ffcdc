"""``python -m sonarmap.evaluate``: the every-sonar segmentation and ranges tables."""

from sonarmap.evaluate.segmentation import main

raise SystemExit(main())
