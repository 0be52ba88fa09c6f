/* Independent Modbus TCP server (libmodbus) for interoperability tests; serves until killed.
 *   cc -o modbus_server tests/peers/modbus_server.c $(pkg-config --cflags --libs libmodbus)
 *   ./modbus_server PORT [VALUE]      (127.0.0.1 only; prints READY when listening)
 * Holding registers (protocol address; mbpoll -r is 1-based): 0-1 VALUE float32 ABCD (big-endian
 * words: mbpoll -B), 2-3 VALUE float32 CDAB (mbpoll's default), 4 = 1234; coils 0-7 = 10100000.
 * Words are set by hand: libmodbus' modbus_set_float_abcd() & co. swap bytes version-dependently. */
#include <modbus.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>
int main(int argc, char **argv) {
    int port = argc > 1 ? atoi(argv[1]) : 1502, s, c, n;
    float v = argc > 2 ? (float)atof(argv[2]) : 3.14159f;
    uint32_t u; uint8_t q[MODBUS_TCP_MAX_ADU_LENGTH];
    modbus_t *ctx = modbus_new_tcp("127.0.0.1", port);
    modbus_mapping_t *map = modbus_mapping_new(8, 0, 16, 0);
    if (!ctx || !map || (s = modbus_tcp_listen(ctx, 1)) < 0) { perror("modbus"); return 1; }
    memcpy(&u, &v, 4);
    map->tab_registers[0] = map->tab_registers[3] = u >> 16;
    map->tab_registers[1] = map->tab_registers[2] = u & 0xffff;
    map->tab_registers[4] = 1234; map->tab_bits[0] = map->tab_bits[2] = 1;
    printf("READY 127.0.0.1:%d\n", port); fflush(stdout);
    for (;;) {
        if ((c = modbus_tcp_accept(ctx, &s)) < 0) return 1;
        while ((n = modbus_receive(ctx, q)) >= 0) if (n > 0) modbus_reply(ctx, q, n, map);
        close(c);
    }
}
