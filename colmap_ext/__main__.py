from colmap_ext.cli import main

raise SystemExit(main())
