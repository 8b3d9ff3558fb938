from humantele.cli import main

raise SystemExit(main())
