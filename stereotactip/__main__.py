from stereotactip.cli import main

raise SystemExit(main())
