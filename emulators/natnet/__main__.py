from emulators.natnet.server import main

raise SystemExit(main())
