from genesis_rl.entry import main

raise SystemExit(main())
