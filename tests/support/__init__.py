"""What the tests share and no test asserts: scripted and fake devices, sessions that received a
welcome, rooms with a recording world, processes started as users start them, device emulators."""
