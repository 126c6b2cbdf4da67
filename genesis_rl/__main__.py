from genesis_rl.cli import main

raise SystemExit(main())
