from dm2_backend.cli.main import main

if __name__ == "__main__":
    main()
