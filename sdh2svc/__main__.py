from sdh2svc.entry import main

main()
