"""`python -m sitl_bridge.envs [FILE...]`: print each scenario's manual (Markdown)."""

from sitl_bridge.envs.manual import main

raise SystemExit(main())
