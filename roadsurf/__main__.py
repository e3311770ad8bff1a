from roadsurf.cli import main

main()
