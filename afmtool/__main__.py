from afmtool.cli.main import main

main()
