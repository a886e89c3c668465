/*
 * harness.c: runs the floornav Uno firmware inside simavr for the firmware tests.
 *
 * Usage: harness [--no-pace] [--start-now] path/to/floornav_uno.elf
 *
 * - Simulates an ATmega328P at 16 MHz with UART0 on a fresh pty and prints
 *   "PTY /dev/pts/N" on stdout (use this path: simavr's /tmp/simavr-uart0 symlink
 *   clashes between parallel runs).
 * - Starts the CPU only after the line "START" arrives on stdin, so the host can open
 *   the pty first (pyserial flushes input on open and the boot banner would be lost).
 *   --start-now skips that wait.
 * - Paces simulated time to wall-clock time, so millis() in the firmware matches the
 *   host's clock (--no-pace runs as fast as it can).
 * - Prints "MOTOR t_ms=<simulated ms> left=<signed pwm> right=<signed pwm>" whenever
 *   the motor outputs change, decoded from the Timer1 registers and the direction pins
 *   (wiring in firmware/README.md). A change is reported once it has held for 100 us of
 *   simulated time, stamped with the time it first appeared: the firmware sets the pins
 *   one after another and the half-set states in between are not real commands.
 * - stdin commands: "START"; "ENC <left_hz> <right_hz>" drives quadrature encoder
 *   signals (channel A rising edges per second, the sign is the direction) on pins
 *   2/4 (left) and 3/5 (right); "ENCPOS <left> <right>" sets where each encoder's
 *   count must get to (cycles of channel A since start, signed) and spreads the
 *   edges still owed over the time since the previous ENCPOS, so the firmware counts
 *   exactly what a host-side plant counted, whenever the lines arrive; "QUIT". End of
 *   stdin or SIGTERM/SIGINT exits.
 * - Exits with _exit(): uart_pty_stop() can hang waiting for its thread.
 */
#define _GNU_SOURCE
#include <signal.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>
#include <pthread.h>

#include "sim_avr.h"
#include "sim_elf.h"
#include "sim_io.h"
#include "sim_irq.h"
#include "avr_ioport.h"
#include "avr_uart.h"
#include "parts/uart_pty.h"

#define MCU "atmega328p"
#define FREQUENCY 16000000u
#define PACE_CHECK_CYCLES 1600u     /* look at the wall clock every 100 us simulated */
#define MAX_LAG_CYCLES (FREQUENCY / 10) /* >100 ms behind (host stalled): stop catching up */
#define SETTLE_CYCLES 1600u         /* a motor output must hold 100 us to be reported */

/* Uno wiring (firmware/README.md): data-space addresses of the ATmega328P registers. */
#define REG_PORTB 0x25
#define REG_PORTD 0x2B
#define REG_TCCR1A 0x80
#define REG_OCR1AL 0x88
#define REG_OCR1BL 0x8A
#define COM1A1 (1 << 7)
#define COM1B1 (1 << 5)

static atomic_int quit_requested;
static atomic_int start_requested;
static atomic_int enc_hz[2];        /* set by the stdin thread, read by the CPU loop */
static atomic_int enc_generation;
static _Atomic long long enc_target[2]; /* ENCPOS counts, read by the CPU loop */
static atomic_int target_generation;

static void on_signal(int sig) {
	(void)sig;
	atomic_store(&quit_requested, 1);
}

static void *stdin_reader(void *arg) {
	(void)arg;
	char line[128];
	while (fgets(line, sizeof line, stdin)) {
		int left, right;
		long long left_count, right_count;
		if (strncmp(line, "START", 5) == 0) {
			atomic_store(&start_requested, 1);
		} else if (sscanf(line, "ENC %d %d", &left, &right) == 2) {
			atomic_store(&enc_hz[0], left);
			atomic_store(&enc_hz[1], right);
			atomic_fetch_add(&enc_generation, 1);
		} else if (sscanf(line, "ENCPOS %lld %lld", &left_count, &right_count) == 2) {
			atomic_store(&enc_target[0], left_count);
			atomic_store(&enc_target[1], right_count);
			atomic_fetch_add(&target_generation, 1);
		} else if (strncmp(line, "QUIT", 4) == 0) {
			break;
		} else {
			fprintf(stderr, "harness: unknown command: %s", line);
		}
	}
	atomic_store(&quit_requested, 1);
	return NULL;
}

/* ---- motor outputs ---------------------------------------------------------------- */

/* Duty 0..255 of a Timer1 pin: the compare register while the pin is in PWM mode,
 * else the port bit (analogWrite() of 0 or 255 switches PWM off and sets the pin). */
static int pwm_duty(avr_t *avr, uint8_t com_bit, uint8_t ocr, uint8_t portb_bit) {
	if (avr->data[REG_TCCR1A] & com_bit)
		return avr->data[ocr];
	return (avr->data[REG_PORTB] & portb_bit) ? 255 : 0;
}

static int direction(int in1, int in2) {
	return (in1 && !in2) ? 1 : (in2 && !in1) ? -1 : 0;
}

static void read_motors(avr_t *avr, int *left, int *right) {
	uint8_t portb = avr->data[REG_PORTB], portd = avr->data[REG_PORTD];
	/* left: PWM D9 = PB1 (OC1A), IN1 D7 = PD7, IN2 D8 = PB0 */
	*left = direction(portd & (1 << 7), portb & (1 << 0)) *
		pwm_duty(avr, COM1A1, REG_OCR1AL, 1 << 1);
	/* right: PWM D10 = PB2 (OC1B), IN1 D11 = PB3, IN2 D12 = PB4 */
	*right = direction(portb & (1 << 3), portb & (1 << 4)) *
		pwm_duty(avr, COM1B1, REG_OCR1BL, 1 << 2);
}

static struct {
	int left, right;                /* last reported */
	int cand_left, cand_right;      /* a different state waiting to settle */
	int has_cand;
	avr_cycle_count_t cand_since;
} motors;

static void report_motors(avr_cycle_count_t cycle, int left, int right) {
	printf("MOTOR t_ms=%.3f left=%d right=%d\n",
	       (double)cycle * 1000.0 / FREQUENCY, left, right);
}

static void poll_motors(avr_t *avr) {
	int left, right;
	read_motors(avr, &left, &right);
	if (left == motors.left && right == motors.right) {
		motors.has_cand = 0;
		return;
	}
	if (!motors.has_cand || left != motors.cand_left || right != motors.cand_right) {
		motors.cand_left = left;
		motors.cand_right = right;
		motors.cand_since = avr->cycle;
		motors.has_cand = 1;
		return;
	}
	if (avr->cycle - motors.cand_since >= SETTLE_CYCLES) {
		motors.left = left;
		motors.right = right;
		motors.has_cand = 0;
		report_motors(motors.cand_since, left, right);
	}
}

/* ---- encoders --------------------------------------------------------------------- */

/* Quadrature: (A, B) steps 00 -> 10 -> 11 -> 01 forward (A leads, B low at A's rising
 * edge) and the other way round backward. */
static const int QUAD_A[4] = {0, 1, 1, 0};
static const int QUAD_B[4] = {0, 0, 1, 1};

static struct {
	avr_irq_t *pin_a, *pin_b;
	int step;                       /* +1, -1 or 0 (stopped) */
	avr_cycle_count_t quarter;      /* cycles between edges */
	avr_cycle_count_t next;
	int phase;
	long long position;             /* quarter steps taken since start, signed */
	int to_target;                  /* ENCPOS mode: stop stepping at target */
	long long target;               /* ENCPOS mode: where position must get to */
} enc[2];

/* ENCPOS spreads the edges owed over the time since the previous one (the host's
 * period), within these bounds. */
#define TARGET_MIN_SPREAD_CYCLES (FREQUENCY / 200)  /* 5 ms */
#define TARGET_MAX_SPREAD_CYCLES (FREQUENCY / 5)    /* 200 ms */
/* ...and no faster than 20 000 quarter steps (5 000 counts) a second, ten times a
 * fast wheel's rate, so a catch-up after a long host stall stays countable by the
 * firmware's interrupts; the next ENCPOS takes up what is still owed. */
#define TARGET_MIN_QUARTER_CYCLES (FREQUENCY / 20000)
static avr_cycle_count_t last_target_cycle;

/* The encoders drive PD2-PD5 from outside, as a real encoder's outputs do. Told so
 * (simavr's "external" pins), simavr keeps their levels when the firmware writes PORTD;
 * else every write (digitalWrite of pin 7, a motor direction) re-applies the internal
 * pull-ups the firmware enables on them, raising A and B to 1 until the next step:
 * false edges (the firmware counted 5-8 % short with DRIVE frames at 30 Hz). */
#define ENCODER_PINS_D 0x3C

static void drive_encoder_pins(avr_t *avr) {
	avr_ioport_external_t levels = {
		.name = 'D',
		.mask = ENCODER_PINS_D,
		.value = (QUAD_A[enc[0].phase] << 2) | (QUAD_A[enc[1].phase] << 3) |
			 (QUAD_B[enc[0].phase] << 4) | (QUAD_B[enc[1].phase] << 5),
	};
	avr_ioctl(avr, AVR_IOCTL_IOPORT_SET_EXTERNAL('D'), &levels);
}

static void setup_encoders(avr_t *avr) {
	uint32_t port_d = AVR_IOCTL_IOPORT_GETIRQ('D');
	enc[0].pin_a = avr_io_getirq(avr, port_d, 2);
	enc[0].pin_b = avr_io_getirq(avr, port_d, 4);
	enc[1].pin_a = avr_io_getirq(avr, port_d, 3);
	enc[1].pin_b = avr_io_getirq(avr, port_d, 5);
	/* Start with A and B high, where the firmware's pull-ups held them before: simavr
	 * polls an external-interrupt pin every cycle while it is low (a level-triggered
	 * check it runs whatever the mode), which slowed the idle board to 0.74x real time. */
	enc[0].phase = enc[1].phase = 2;
	drive_encoder_pins(avr);
}

static void update_encoder_rates(avr_t *avr) {
	for (int i = 0; i < 2; i++) {
		int hz = atomic_load(&enc_hz[i]);
		enc[i].to_target = 0;
		enc[i].step = hz > 0 ? 1 : hz < 0 ? -1 : 0;
		if (hz) {
			enc[i].quarter = FREQUENCY / (4u * (unsigned)abs(hz));
			if (enc[i].quarter == 0)
				enc[i].quarter = 1;
			enc[i].next = avr->cycle + enc[i].quarter;
		}
	}
}

/* A rate ("ENC") drops the quarter step under way at each change, and a host that
 * computes it over its nominal period miscounts when it wakes late: the count drifts
 * from the plant's. A target ("ENCPOS") owes exact edges, whenever it arrives. */
static void update_encoder_targets(avr_t *avr) {
	avr_cycle_count_t spread = avr->cycle - last_target_cycle;
	if (spread < TARGET_MIN_SPREAD_CYCLES)
		spread = TARGET_MIN_SPREAD_CYCLES;
	if (spread > TARGET_MAX_SPREAD_CYCLES)
		spread = TARGET_MAX_SPREAD_CYCLES;
	last_target_cycle = avr->cycle;
	for (int i = 0; i < 2; i++) {
		/* One count per cycle of channel A: four quarter steps. */
		long long target = 4 * atomic_load(&enc_target[i]);
		long long owed = target - enc[i].position;
		int was_stepping = enc[i].step != 0;
		enc[i].to_target = 1;
		enc[i].target = target;
		enc[i].step = owed > 0 ? 1 : owed < 0 ? -1 : 0;
		if (!owed)
			continue;
		unsigned long long steps = (unsigned long long)(owed > 0 ? owed : -owed);
		enc[i].quarter = spread / steps;
		if (enc[i].quarter < TARGET_MIN_QUARTER_CYCLES)
			enc[i].quarter = TARGET_MIN_QUARTER_CYCLES;
		if (!was_stepping || enc[i].next > avr->cycle + enc[i].quarter)
			enc[i].next = avr->cycle + enc[i].quarter;
	}
}

static void poll_encoders(avr_t *avr) {
	for (int i = 0; i < 2; i++) {
		if (!enc[i].step || avr->cycle < enc[i].next)
			continue;
		enc[i].phase = (enc[i].phase + enc[i].step) & 3;
		enc[i].position += enc[i].step;
		drive_encoder_pins(avr);
		avr_raise_irq(enc[i].pin_b, QUAD_B[enc[i].phase]);
		avr_raise_irq(enc[i].pin_a, QUAD_A[enc[i].phase]);
		enc[i].next += enc[i].quarter;
		if (enc[i].to_target && enc[i].position == enc[i].target)
			enc[i].step = 0;
	}
}

/* ---- main ------------------------------------------------------------------------- */

static uint64_t now_ns(void) {
	struct timespec ts;
	clock_gettime(CLOCK_MONOTONIC, &ts);
	return (uint64_t)ts.tv_sec * 1000000000u + (uint64_t)ts.tv_nsec;
}

static void usage(const char *argv0) {
	fprintf(stderr, "usage: %s [--no-pace] [--start-now] firmware.elf\n", argv0);
	_exit(2);
}

int main(int argc, char **argv) {
	int pace = 1, start_now = 0;
	const char *elf = NULL;
	for (int i = 1; i < argc; i++) {
		if (!strcmp(argv[i], "--no-pace"))
			pace = 0;
		else if (!strcmp(argv[i], "--start-now"))
			start_now = 1;
		else if (argv[i][0] == '-' || elf)
			usage(argv[0]);
		else
			elf = argv[i];
	}
	if (!elf)
		usage(argv[0]);
	setvbuf(stdout, NULL, _IOLBF, 0);

	/* simavr's loader and uart_pty chat on stdout; keep stdout for our own lines. */
	int saved_stdout = dup(STDOUT_FILENO);
	dup2(STDERR_FILENO, STDOUT_FILENO);

	elf_firmware_t firmware;
	memset(&firmware, 0, sizeof firmware);
	if (elf_read_firmware(elf, &firmware) != 0) {
		fprintf(stderr, "harness: cannot read %s\n", elf);
		_exit(1);
	}
	avr_t *avr = avr_make_mcu_by_name(MCU);
	if (!avr) {
		fprintf(stderr, "harness: simavr does not know %s\n", MCU);
		_exit(1);
	}
	avr_init(avr);
	avr_load_firmware(avr, &firmware);
	avr->frequency = FREQUENCY;     /* Arduino ELFs carry no .mmcu section */

	static uart_pty_t uart;
	uart_pty_init(avr, &uart);
	uart_pty_connect(&uart, '0');
	fflush(stdout);
	dup2(saved_stdout, STDOUT_FILENO);
	close(saved_stdout);
	/* By default simavr's UART sleeps the host thread when the firmware polls an empty
	 * receiver; that would skew the pacing. */
	uint32_t flags = 0;
	avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
	flags &= ~(AVR_UART_FLAG_POLL_SLEEP | AVR_UART_FLAG_STDIO);
	avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
	setup_encoders(avr);

	struct sigaction sa;
	memset(&sa, 0, sizeof sa);
	sa.sa_handler = on_signal;
	sigaction(SIGTERM, &sa, NULL);
	sigaction(SIGINT, &sa, NULL);
	pthread_t reader;
	pthread_create(&reader, NULL, stdin_reader, NULL);

	printf("PTY %s\n", uart.pty.slavename);
	while (!start_now && !atomic_load(&start_requested) && !atomic_load(&quit_requested))
		usleep(2000);
	if (atomic_load(&quit_requested))
		_exit(0);
	printf("STARTED\n");
	report_motors(avr->cycle, 0, 0);

	uint64_t wall0 = now_ns();
	avr_cycle_count_t cycle0 = avr->cycle, next_check = avr->cycle + PACE_CHECK_CYCLES;
	int generation = 0, targets = 0, status = 0;
	last_target_cycle = avr->cycle;
	while (!atomic_load(&quit_requested)) {
		int state = avr_run(avr);
		if (state == cpu_Done || state == cpu_Crashed) {
			printf("EXIT cpu %s\n", state == cpu_Done ? "done" : "crashed");
			status = state == cpu_Crashed;
			break;
		}
		poll_motors(avr);
		poll_encoders(avr);
		if (avr->cycle < next_check)
			continue;
		next_check = avr->cycle + PACE_CHECK_CYCLES;
		int g = atomic_load(&enc_generation);
		if (g != generation) {
			generation = g;
			update_encoder_rates(avr);
		}
		int t = atomic_load(&target_generation);
		if (t != targets) {
			targets = t;
			update_encoder_targets(avr);
		}
		if (!pace)
			continue;
		uint64_t wall = now_ns();
		avr_cycle_count_t due = cycle0 + (wall - wall0) * (FREQUENCY / 1000000u) / 1000u;
		if (avr->cycle > due) {
			uint64_t ahead_ns = (avr->cycle - due) * 1000u / (FREQUENCY / 1000000u);
			if (ahead_ns > 100000000u)
				ahead_ns = 100000000u;
			struct timespec ts = {0, (long)ahead_ns};
			if (ahead_ns >= 50000)  /* nap only when it is worth a syscall */
				nanosleep(&ts, NULL);
		} else if (due - avr->cycle > MAX_LAG_CYCLES) {
			wall0 = wall;           /* the host stalled: forget the lost time */
			cycle0 = avr->cycle;
		}
	}
	fflush(stdout);
	_exit(status);
}
