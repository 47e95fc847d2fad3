from afmtool.cli.entry import main

main()
