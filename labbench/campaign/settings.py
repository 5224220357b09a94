"""The rig's ``[campaign]`` table: what a campaign does between its points on this bench.

```toml
[campaign]
pause_s = 2.0      # force zero, device closed, this long before the next point opens it
```

``pause_s`` [s] (0-600; default 2 s on real hardware, 0 on a simulator): after a point
the runner has commanded zero force, disabled and closed the device; the campaign waits
this long (a handle still swinging settles, a drive cools, the operator sees the pause)
before it opens the device for the next point. A stop request ends the wait at once.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from labbench.errors import UserError, unknown_name

TABLE = "campaign"
MAX_PAUSE_S = 600.0
HARDWARE_PAUSE_S = 2.0


@dataclass(frozen=True)
class CampaignSettings:
    pause_s: float

    @classmethod
    def from_rig(cls, rig, simulated: bool = False) -> CampaignSettings:
        """The rig's ``[campaign]`` table over the defaults (module doc); one UserError naming
        the file and the field."""
        table = rig.section(TABLE)
        for name in table:
            if name != "pause_s":
                raise UserError(f"{rig.source}: [{TABLE}] {unknown_name('field', name, ('pause_s',))}")
        pause = table.get("pause_s", 0.0 if simulated else HARDWARE_PAUSE_S)
        ok = isinstance(pause, (int, float)) and not isinstance(pause, bool) and math.isfinite(pause)
        if not ok or not 0 <= pause <= MAX_PAUSE_S:
            raise UserError(f"{rig.source}: [{TABLE}] pause_s must be a number of seconds in "
                            f"[0, {MAX_PAUSE_S:g}], got {pause!r}")
        return cls(float(pause))
